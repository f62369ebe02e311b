"""The Dask worker plugin that gives each worker process its own database engine.

In a module of its own, which imports little: ``packings enumerate`` hands it to the local
cluster's workers as they start, and so imports it before they can start.
"""

from __future__ import annotations

import gc

from distributed import WorkerPlugin
from sqlalchemy import Engine

from packings.db import advisory_key, display_url, make_engine, parse_url, sessions


def plugin_name(url: str) -> str:
    """One plugin (and so one engine per worker process) per database."""
    return f"packings-db-{advisory_key(display_url(parse_url(url))) & 0xFFFFFFFF:08x}"


def prepare_process() -> float:
    """Import the tasks' modules and warm the compiled kernels up in this process; returns the warm-up's
    seconds (a few milliseconds where it was done already, e.g. in a worker forked from the fork server
    that ran it: :mod:`packings.preload`).

    Pays the imports and the kernels' compilation (or numba cache load) once per worker, not per task.
    """
    import packings.tasks  # noqa: F401 - the tasks' module
    from packings.workers.expand import warm_up  # the tasks import it when they first run

    seconds = warm_up()
    # What is loaded now lives as long as the process: keep it out of the garbage collector's full
    # passes, and out of its last one when the process exits (0.2-0.3 s: the cluster's close waits for it).
    gc.freeze()
    return seconds


class LocalWorkerPlugin(WorkerPlugin):
    """Sets up each worker process of a local cluster (one that ``packings enumerate`` starts): they
    ignore SIGINT.  Ctrl-C in a terminal reaches the whole process group; the coordinator alone answers
    it, putting its leases back and closing the cluster, which stops the workers; on their own they
    would each print a traceback of their event loop."""

    name = "packings-local-worker"

    def setup(self, worker) -> None:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)


class DatabasePlugin(WorkerPlugin):
    """Creates the database engine once per worker process."""

    def __init__(self, url: str):
        self.url = url
        self.name = plugin_name(url)
        self.engine: Engine | None = None

    def setup(self, worker) -> None:
        self.engine = make_engine(self.url)
        self.sessions = sessions(self.engine)
        self.readers = sessions(self.engine, readonly=True)  # SQLite: reading a task takes no write lock
        self.warm_up_seconds = prepare_process()

    def teardown(self, worker) -> None:
        if self.engine is not None:
            self.engine.dispose()
