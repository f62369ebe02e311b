"""The Dask side: one task per few expansions, and the plugin that gives each
worker process its own database engine.

A task receives only a few (expansion id, lease token) pairs and the name of
the plugin holding the engine; it reads their clusters and the run's
parameters from the database (one read-only query), and for each runs
:func:`workers.expand.expand` and writes the result back with
:func:`service.store.record_expansion` (one transaction per expansion, guarded
by its lease token).  Engines are never pickled into tasks.
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
        self.readers = sessions(self.engine, readonly=True)  # SQLite: reading a task takes no write lock
        # Pay the imports and the kernels' compilation (or numba cache load) once per worker, not per task.
        import workers.expand  # noqa: F401
        from workers.kernels import warm_up

        self.warm_up_seconds = warm_up()

    def teardown(self, worker) -> None:
        if self.engine is not None:
            self.engine.dispose()


def run_expansion(Session_, expansion_id: int, token: str, worker: str = "", Reader=None) -> dict:
    """Expand one leased cluster and write the result back; idempotent.

    Returns the write-back summary, or ``{"expansion": id, "stale": True}``
    when the lease is not (or no longer) ``token``'s, in which case nothing is
    written.  The task is read with ``Reader`` sessions if given (read-only
    ones: the lease is checked again when the result is written).
    """
    task = store.load_task(Reader or Session_, expansion_id, token)
    if task is None:
        return {"expansion": expansion_id, "stale": True}
    return run_loaded(Session_, task, token, worker)


def run_loaded(Session_, task: store.Task, token: str, worker: str = "") -> dict:
    """:func:`run_expansion` of a task already read (:func:`service.store.load_tasks`)."""
    t0 = time.perf_counter()
    ex = expand(task.cluster, task.params)
    seconds = time.perf_counter() - t0
    summary = store.record_expansion(Session_, task, token, ex, seconds, worker or store.process_name())
    return summary if summary is not None else {"expansion": task.expansion_id, "stale": True}


class ExpansionsFailed(Exception):
    """Some expansions of a task failed: ``args[0]`` maps each one's id to its error's first line.
    The task's other expansions were written back (or were stale)."""

    @property
    def errors(self) -> dict[int, str]:
        return self.args[0]

    def __str__(self) -> str:
        return "; ".join(f"expansion {eid}: {err}" for eid, err in self.errors.items())


def error_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".splitlines()[0]


def expand_task(expansions: list[tuple[int, str]], plugin: str) -> list[dict]:
    """The Dask task: :func:`run_expansion` for each (expansion id, lease token) in turn, with this
    worker's engine (all read in one query first); each is written back in its own transaction.  One
    that fails does not stop the others; if any failed, the task raises :class:`ExpansionsFailed` at
    the end, naming them."""
    w = get_worker()
    p = w.plugins[plugin]
    tasks = store.load_tasks(p.readers, expansions)  # one read for all (each lease is checked again on write)
    out, errors = [], {}
    for expansion_id, token in expansions:
        if expansion_id not in tasks:
            out.append({"expansion": expansion_id, "stale": True})
            continue
        try:
            out.append(run_loaded(p.sessions, tasks[expansion_id], token, worker=w.address))
        except Exception as exc:  # noqa: BLE001 - reported to the coordinator, which retries or fails it
            errors[expansion_id] = error_line(exc)
    if errors:
        raise ExpansionsFailed(errors)
    return out
