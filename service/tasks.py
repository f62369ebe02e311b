"""The Dask side: one task per few expansions, run with the database engine that
:class:`service.plugin.DatabasePlugin` gives each worker process.

A task receives only a few (expansion id, lease token) pairs and the name of
the plugin holding the engine; it reads their clusters and the run's
parameters from the database (one read-only query), and for each runs
:func:`workers.expand.expand` and writes the result back with
:func:`service.store.record_expansion` (one transaction per expansion, guarded
by its lease token).  Engines are never pickled into tasks.
"""

from __future__ import annotations

import time

from distributed import get_worker

from service import store
from workers.expand import expand


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
