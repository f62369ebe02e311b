"""The Dask side: one task per few expansions, run with the database engine that
:class:`packings.service.plugin.DatabasePlugin` gives each worker process.

A task receives only a few (expansion id, lease token) pairs and the name of
the plugin holding the engine; it reads their clusters and the run's
parameters from the database (one read-only query), runs
:func:`packings.workers.expand.expand` on each, and writes the results back with
:func:`packings.service.store.record_expansions` (one transaction for the task, each
expansion guarded by its own lease token).  Engines are never pickled into
tasks.
"""

from __future__ import annotations

import time
import traceback

from distributed import get_worker

from packings.service import store
from packings.service.owners import process_name


def expand(cluster, params, arrivals=()):
    """:func:`packings.workers.expand.expand`, imported when first called: the coordinator imports this module (to
    submit its tasks) and never expands, so it never loads the path-following code and numba.  ``arrivals``:
    the rows of :attr:`packings.service.store.Task.arrivals`, whose paths are taken from the end they arrived at."""
    from packings.workers.expand import arrivals as by_contact
    from packings.workers.expand import expand as expand_cluster

    return expand_cluster(cluster, params, arrivals=by_contact(arrivals))


def run_expansion(Session_, expansion_id: int, token: str, worker: str = "", Reader=None) -> dict:
    """Expand one leased cluster and write the result back; idempotent.

    Returns the write-back summary, or ``{"expansion": id, "stale": True}``
    when the lease is not (or no longer) ``token``'s, in which case nothing is
    written.  The task is read with ``Reader`` sessions if given (read-only
    ones: the lease is checked again when the result is written).
    """
    task = store.load_task(Reader or Session_, expansion_id, token)
    summary = (
        None
        if task is None
        else store.record_expansions(Session_, [run_loaded(task, token)], worker or process_name())[0]
    )
    return summary if summary is not None else stale(expansion_id)


def stale(expansion_id: int) -> dict:
    """The summary of an expansion whose lease is not (or no longer) its task's: nothing was written."""
    return {"expansion": expansion_id, "stale": True}


def run_loaded(task: store.Task, token: str) -> store.Finished:
    """:func:`packings.workers.expand.expand` of a task already read (:func:`packings.service.store.load_tasks`), timed."""
    t0 = time.perf_counter()
    ex = expand(task.cluster, task.params, task.arrivals)
    return store.Finished(task, token, ex, time.perf_counter() - t0)


class ExpansionsFailed(Exception):
    """Some expansions of a task failed: ``args[0]`` maps each one's id to its error's traceback.
    The task's other expansions were written back (or were stale)."""

    @property
    def errors(self) -> dict[int, str]:
        return self.args[0]

    def __str__(self) -> str:
        return "; ".join(f"expansion {eid}: {summary(err)}" for eid, err in self.errors.items())


def error_line(exc: BaseException) -> str:
    """``Type: message``, its first line."""
    return f"{type(exc).__name__}: {exc}".splitlines()[0]


def error_text(exc: BaseException) -> str:
    """The full traceback of ``exc``, as the database keeps it for a failed expansion (the command line
    prints :func:`summary` of it)."""
    return "".join(traceback.format_exception(exc)).rstrip()


def summary(error: str) -> str:
    """The one line of a stored error: for a traceback, the first line of the exception it ends with
    (``Type: message``, the line after its last indented frame line), else the error's first line."""
    lines = [ln for ln in error.strip().splitlines() if ln.strip()]
    if not lines:
        return ""
    if lines[0].startswith("Traceback (most recent call last)"):
        frames = [i for i, ln in enumerate(lines) if ln.startswith((" ", "\t"))]
        return lines[frames[-1] + 1 if frames and frames[-1] + 1 < len(lines) else -1].strip()
    return lines[0]


def expand_task(expansions: list[tuple[int, str]], plugin: str) -> list[dict]:
    """The Dask task: expand each (expansion id, lease token) in turn, with this worker's engine (all
    read in one query first), and write them back together in one transaction
    (:func:`packings.service.store.record_expansions`; a stale lease's expansion is left out of it).  One whose
    expansion fails does not stop the others; if any failed (or the write-back did, and so all of
    them), the task raises :class:`ExpansionsFailed` at the end, naming them."""
    w = get_worker()
    p = w.plugins[plugin]
    tasks = store.load_tasks(p.readers, expansions)  # one read for all (each lease is checked again on write)
    finished, errors = [], {}
    for expansion_id, token in expansions:
        if expansion_id in tasks:
            try:
                finished.append(run_loaded(tasks[expansion_id], token))
            except Exception as exc:  # noqa: BLE001 - reported to the coordinator, which retries or fails it
                errors[expansion_id] = error_text(exc)
    written: dict[int, dict] = {}
    if finished:
        try:
            summaries = store.record_expansions(p.sessions, finished, w.address)
        except Exception as exc:  # noqa: BLE001 - nothing was written: all of them are retried
            errors.update(dict.fromkeys((f.task.expansion_id for f in finished), error_text(exc)))
        else:
            written = {f.task.expansion_id: summary for f, summary in zip(finished, summaries) if summary is not None}
    if errors:
        raise ExpansionsFailed(errors)
    return [written.get(eid) or stale(eid) for eid, _ in expansions]
