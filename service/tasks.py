"""The Dask side: one task per expansion, and the plugin that gives each
worker process its own database engine.

The task receives only an expansion id, its lease token and the name of the
plugin holding the engine; it reads the cluster and the run's parameters from
the database, runs :func:`workers.expand.expand`, and writes the result back
with :func:`service.store.record_expansion` (one transaction, guarded by the
lease token).  Engines are never pickled into tasks.
"""

from __future__ import annotations

import time

from distributed import WorkerPlugin, get_worker
from sqlalchemy import Engine

from service import store
from service.db import advisory_key, display_url, make_engine, parse_url, sessions
from workers.expand import expand


def plugin_name(url: str) -> str:
    """One plugin (and so one engine per worker process) per database."""
    return f"packings-db-{advisory_key(display_url(parse_url(url))) & 0xFFFFFFFF:08x}"


class DatabasePlugin(WorkerPlugin):
    """Creates the database engine once per worker process."""

    def __init__(self, url: str):
        self.url = url
        self.name = plugin_name(url)
        self.engine: Engine | None = None

    def setup(self, worker) -> None:
        self.engine = make_engine(self.url)
        self.sessions = sessions(self.engine)
        # Pay the imports and the kernels' compilation (or numba cache load) once per worker, not per task.
        import workers.expand  # noqa: F401
        from workers.kernels import warm_up

        self.warm_up_seconds = warm_up()

    def teardown(self, worker) -> None:
        if self.engine is not None:
            self.engine.dispose()


def run_expansion(Session_, expansion_id: int, token: str, worker: str = "") -> dict:
    """Expand one leased cluster and write the result back; idempotent.

    Returns the write-back summary, or ``{"expansion": id, "stale": True}``
    when the lease is not (or no longer) ``token``'s, in which case nothing is
    written.
    """
    task = store.load_task(Session_, expansion_id, token)
    if task is None:
        return {"expansion": expansion_id, "stale": True}
    t0 = time.perf_counter()
    ex = expand(task.cluster, task.params)
    seconds = time.perf_counter() - t0
    summary = store.record_expansion(Session_, task, token, ex, seconds, worker or store.process_name())
    return summary if summary is not None else {"expansion": expansion_id, "stale": True}


def expand_task(expansion_id: int, token: str, plugin: str) -> dict:
    """The Dask task: run :func:`run_expansion` with this worker's engine."""
    w = get_worker()
    p = w.plugins[plugin]
    return run_expansion(p.sessions, expansion_id, token, worker=w.address)
