"""The Dask plugins of a run: the worker plugin that gives each worker process its own database
engine, and the scheduler plugin that keeps what Dask remembers of tasks long gone bounded.

In a module of its own, which imports little: ``packings enumerate`` hands them to the local
cluster as it starts, and so imports it before it can start.
"""

from __future__ import annotations

import gc
import signal
import threading

from dask.utils import key_split
from distributed import SchedulerPlugin, WorkerPlugin
from sqlalchemy import Engine

from packings.service.db import advisory_key, display_url, make_engine, parse_url, sessions


def plugin_name(url: str) -> str:
    """One plugin (and so one engine per worker process) per database."""
    return f"packings-db-{advisory_key(display_url(parse_url(url))) & 0xFFFFFFFF:08x}"


def prepare_process() -> float:
    """Import the tasks' modules and warm the compiled kernels up in this process; returns the warm-up's
    seconds (a few milliseconds where it was done already, e.g. in a worker forked from the fork server
    that ran it: :mod:`packings.service.preload`).

    Pays the imports and the kernels' compilation (or numba cache load) once per worker, not per task.
    """
    # here, not at the top: the command imports this module before its cluster starts, and loads no numerics
    import packings.service.tasks  # noqa: F401 - the tasks' module
    from packings.workers.expand import warm_up  # the tasks import it when they first run

    seconds = warm_up()
    # What is loaded now lives as long as the process: keep it out of the garbage collector's full
    # passes, and out of its last one when the process exits (0.2-0.3 s: the cluster's close waits for it).
    gc.freeze()
    return seconds


def dask_setup(worker) -> None:
    """``dask worker --preload packings.service.plugin``: each worker process imports the tasks' modules
    and warms the compiled kernels up (:func:`prepare_process`) before it joins its scheduler, rather than
    as the database plugin reaches it.  A nanny imports the module to read its options, and loads nothing
    more: only the worker processes run this.  Slurm's worker jobs start so (:mod:`packings.service.slurm`)."""
    prepare_process()


#: how many task keys Dask's ``key_split`` may remember in a process before its cache is emptied
KEY_CACHE_LIMIT = 1_000


def bound_key_cache() -> None:
    """Empty the cache of ``dask.utils.key_split`` once it holds more than :data:`KEY_CACHE_LIMIT` keys.

    Dask splits every task's key (into the prefix its panels show) in the scheduler, the Client and each
    worker, through a cache of up to 100,000 keys that holds each key and its prefix (about 190 bytes a
    key).  Each task of a run has a key of its own, never split again once the task is done, so the
    cache only grows: by up to 19 MiB in each process over a run of 100,000 tasks.  Emptied, it costs
    the keys of the tasks in flight one split each again (a few microseconds)."""

    if key_split.cache_info().currsize > KEY_CACHE_LIMIT:
        key_split.cache_clear()


def _distinct(items: list) -> list:
    """``items`` without repeats (dicts: no set), in their order."""
    out: list = []
    for x in items:
        if x not in out:
            out.append(x)
    return out


class TaskLeftovers(SchedulerPlugin):
    """What Dask's scheduler keeps of every task it was given, after the task is gone, kept bounded.

    * Each submission adds its kind of collection (``{"type": "Future"}`` for each ``Client.submit``) to
      the metadata of the span its tasks join (the default span, for all of a run's tasks), a list Dask
      never shortens: one dict a task, for as long as the scheduler lives.  After each submission the
      list of each span it touched keeps one entry of each kind.
    * The cache of task keys (:func:`bound_key_cache`) in the scheduler's process.

    ``packings enumerate`` registers it on its local cluster and on an existing scheduler (which then
    needs the package installed); ``dask scheduler --preload packings.service.dashboard`` adds it too
    (docs/performance.md)."""

    name = "packings-task-leftovers"
    idempotent = True

    def update_graph(self, scheduler, *, tasks=(), **kwargs) -> None:
        spans = {scheduler.tasks[k].group.span_id for k in tasks if k in scheduler.tasks}
        found = getattr(scheduler.extensions.get("spans"), "spans", {})
        for span_id in spans:
            meta = getattr(found.get(span_id), "metadata", None) or {}
            kinds = meta.get("collections")
            if kinds is not None and len(kinds) > 1:
                kinds[:] = _distinct(kinds)
        bound_key_cache()


def serves_page(dask_scheduler) -> bool:
    """Whether this scheduler serves the packings page (``client.run_on_scheduler(serves_page)``): one
    started with ``--preload packings.service.dashboard``, or a local cluster's
    (:func:`packings.service.dashboard.serve_json` marks it)."""
    return bool(getattr(dask_scheduler, "packings_page", False))


class LocalWorkerPlugin(WorkerPlugin):
    """Sets up each worker process of a local cluster (one that ``packings enumerate`` starts): they
    ignore SIGINT.  Ctrl-C in a terminal reaches the whole process group; the coordinator alone answers
    it, putting its leases back and closing the cluster, which stops the workers; on their own they
    would each print a traceback of their event loop."""

    name = "packings-local-worker"

    def setup(self, worker) -> None:
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

    def transition(self, key, start, finish, **kwargs) -> None:
        if finish == "forgotten":  # the worker's cache of task keys, as the scheduler's (TaskLeftovers)
            bound_key_cache()

    def teardown(self, worker) -> None:
        if self.engine is not None:
            self.engine.dispose()
