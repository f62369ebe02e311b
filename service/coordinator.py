"""The coordinator: drives one run from the frontier in the database.

It claims pending expansions in batches sized to the workers, submits them as
Dask tasks of up to ``batch`` expansions each (fewer, while a claim takes all
that is pending: at the start and the end of a run), consumes results as they
complete and claims more, until nothing is pending or leased.  A task writes
its expansions back in one transaction, each guarded by its lease token.  The
Dask side (the tasks in flight, the scheduler reached again when it is lost, the
watchdog, each task's end sorted) is :class:`packings.service.driver.Driver`'s;
what is a run's own (leases, retries, tasks sent alone, the heartbeat, the lost
workers counted) is here, in its subclass :class:`_Run`.

Failures are of two kinds:

* an expansion that fails (``expand`` or its write-back raised) is put back to
  pending and retried, at most ``max_attempts`` times in all, then marked
  failed with its error's traceback;
* a task lost to the infrastructure (its worker died, :func:`packings.service.driver.infrastructure`,
  or the scheduler forgot it) says nothing about its expansions: they go back
  to pending without using up an attempt (``expansions.retries``), and from
  then on each is sent alone in a task of its own.  Only a task lost again
  while it held one expansion alone counts against that expansion
  (``expansions.isolated_failures``): one that kills every worker it runs on
  ends failed, machines that come and go do not end a run.

Everything needed to resume is in the database: a coordinator that is killed
leaves leases behind, and the next one (the same command) puts them back to
pending when it starts, their attempts not used up.  What was recovered is
logged (logger ``packings.service.coordinator``).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Callable

from distributed import Client
from distributed.scheduler import KilledWorker
from sqlalchemy import Engine, select

from packings.service import queries, store
from packings.service.db import sessions
from packings.service.driver import Driver, Every
from packings.service.errors import StorageError
from packings.service.models import DONE, FAILED, LEASED, PENDING, ExpansionRow
from packings.service.owners import process_name
from packings.service.plugin import DatabasePlugin
from packings.service.tasks import ExpansionsFailed, error_line, expand_task, summary
from packings.workers.params import Params

log = logging.getLogger(__name__)

#: what SQLite, PostgreSQL or the system say when the database cannot be written (lower case)
CANNOT_WRITE = (
    "database or disk is full",
    "no space left on device",
    "could not extend file",
    "diskfull",
    "readonly database",
    "read-only transaction",
    "read-only file system",
)

HEARTBEAT_SECONDS = 10.0
PROGRESS_SECONDS = 0.25  #: how often progress is read from the database and shown
PROGRESS_SHARE = 0.05  #: and at most this share of the time, however large the run (driver.Every)
#: expansions per Dask task at most: a task costs the coordinator and Dask's scheduler a few ms of CPU,
#: its worker about 4 ms between tasks and its write-back's fixed part (BEGIN, COMMIT, one query of the
#: stored clusters) once, as much as 5-10 % of an expansion at n = 10-11.  16 rather than 8: at n = 11 on
#: two workers, 0.6 % less of the wall time outside `expand` (five pairs of runs); the last expansions of
#: a run still go out one a task (:func:`_task_count`)
BATCH = 16


@dataclass
class Progress:
    done: int = 0
    pending: int = 0
    leased: int = 0
    failed: int = 0

    @property
    def total(self) -> int:
        return self.done + self.pending + self.leased + self.failed

    @property
    def clusters(self) -> int:
        """Clusters the run has reached: one expansion each."""
        return self.total


@dataclass
class RunResult:
    run_id: int
    n: int
    status: str
    by_contacts: dict[int, int]
    diagnostics: dict
    seconds: float
    resumed: bool
    errors: list[str] = field(default_factory=list)
    total_seconds: float = 0.0  #: the run's time over all its coordinators (``seconds``: this one's)
    #: with ``glued`` (:func:`packings.service.run.enumerate`): the reports of the glued catalysis passes made, in order
    catalysis: list = field(default_factory=list)

    @property
    def total(self) -> int:
        return sum(self.by_contacts.values())


def _shares(claimed: list, tasks: int) -> list[list]:
    """``claimed`` cut into at most ``tasks`` consecutive parts of sizes that differ by one at most."""
    k = min(tasks, len(claimed))
    if k <= 0:
        return []
    q, r = divmod(len(claimed), k)
    out, i = [], 0
    for j in range(k):
        size = q + (j < r)
        out.append(claimed[i : i + size])
        i += size
    return out


def _task_count(claimed: int, wanted: int, capacity: int, batch: int) -> int:
    """How many tasks to share ``claimed`` expansions out among: the ``wanted`` tasks while the frontier
    is large; when the claim took all that was pending (fewer than ``wanted * batch``), as many as the
    workers hold (``capacity``, one expansion each at least), so that the last expansions of a run (which
    at n = 11 take 0.2-0.5 s each) are not queued in one task on one worker while another has none."""
    if claimed >= wanted * batch:
        return wanted
    return max(wanted, min(claimed, capacity))


class _Heartbeat(threading.Thread):
    """Marks the run as driven by this coordinator every HEARTBEAT_SECONDS,
    however long the tasks take, so that other hosts do not take it over."""

    def __init__(self, Session_, run_id: int, owner: str, seconds: Callable[[], float] | None = None):
        super().__init__(name="packings-heartbeat", daemon=True)
        self.args = (Session_, run_id, owner)
        self.seconds = seconds  #: the run's time so far, recorded with each beat
        self.missed = 0  #: beats that failed (each is retried at the next)
        self.stopped = threading.Event()
        self.start()

    def run(self) -> None:
        while not self.stopped.wait(HEARTBEAT_SECONDS):
            try:
                store.heartbeat(*self.args, self.seconds() if self.seconds else None)
            except Exception as e:  # noqa: BLE001 - a missed beat is retried at the next one
                self.missed += 1
                log.warning("run %d: heartbeat %d missed: %s", self.args[1], self.missed, error_line(e))

    def stop(self) -> None:
        self.stopped.set()
        self.join()


def cannot_write(error: str) -> str | None:
    """The exception line of a failed task's error (or of an error's text), if it says that the
    database cannot be written."""
    line = summary(error)
    return line if any(w in line.lower() for w in CANNOT_WRITE) else None


def not_writable(line: str) -> StorageError:
    return StorageError(
        f"the database cannot be written ({line}): free space or make it writable, then run "
        "the same command again to resume"
    )


def _try(f: Callable) -> None:
    """``f()``, a failure of which is logged, not raised (a clean-up that may fail as what it cleans up did)."""
    try:
        f()
    except Exception as e:  # noqa: BLE001 - logged; what it would have done is done by the next coordinator
        log.warning("%s", error_line(e))


class _Departures:
    """The Dask workers that leave while the run goes on, as the scheduler reports them (its
    ``remove-worker`` event on the topic ``all``, which any scheduler sends to the clients that
    subscribe to it), with the run's tasks each held.

    Dask runs a task lost with its worker again on another one (up to its allowed-failures) without a
    word to the coordinator: a worker lost so would go unseen.  Each one lost (not retired) is logged
    here in one line, and the expansions of the tasks it held are counted in their ``retries`` (as
    expansions put back after a lost task are), which ``packings status`` and the dashboard show.
    ``part_of(key)`` gives the expansions of the run's task ``key`` in flight (None for another's)."""

    TOPIC = "all"

    def __init__(self, client: Client, run_id: int, part_of: Callable[[str], list | None]):
        self.client, self.run_id, self.part_of = client, run_id, part_of
        self.reported: queue.SimpleQueue = queue.SimpleQueue()
        self.counted: set[str] = set()  #: the tasks counted here (lost() does not count them again)
        self.subscribe()

    def subscribe(self) -> None:
        """Ask the scheduler for its events (again, after it was reached again: a restarted one knows no
        subscription)."""
        self.client.subscribe_topic(self.TOPIC, self._event)

    def _event(self, event) -> None:
        """In the Client's event loop, before the result of a task run again elsewhere reaches the
        coordinator (the scheduler sends the event first): which of the run's tasks the worker held."""
        msg = event[1] if isinstance(event, tuple) and len(event) == 2 else event
        if not isinstance(msg, dict) or msg.get("action") != "remove-worker":
            return
        held = {}
        for key in msg.get("processing-tasks") or ():
            part = self.part_of(key)
            if part is not None:
                held[key] = part
        expected = bool(msg.get("expected"))
        if not expected:
            self.counted.update(held)
        self.reported.put((str(msg.get("worker", "?")), expected, list(held.values())))

    def count(self, Session_) -> int:
        """Count and log, in the coordinator's thread, the workers reported gone since the last call;
        returns how many were lost."""
        lost = 0
        while True:
            try:
                worker, expected, parts = self.reported.get_nowait()
            except queue.Empty:
                return lost
            ids = [eid for part in parts for eid, _ in part]
            if expected:  # retired or closed by its operator: its tasks go elsewhere, no fault
                log.info(
                    "run %d: Dask worker %s left (retired); %d task(s) go to other workers",
                    self.run_id,
                    worker,
                    len(parts),
                )
                continue
            lost += 1
            _try(lambda: store.count_retries(Session_, ids))
            log.warning(
                "run %d: Dask worker %s was lost with %d of the run's tasks (%d expansion(s)), which are run "
                "again (counted in retries)",
                self.run_id,
                worker,
                len(parts),
                len(ids),
            )

    def close(self) -> None:
        try:
            self.client.unsubscribe_topic(self.TOPIC)
        except Exception:  # noqa: BLE001 - the Client or its scheduler is gone already
            pass


def _progress(Reader, run_id: int) -> Progress:
    with Reader() as s:
        f = queries.frontier(s, run_id)
    return Progress(f.get(DONE, 0), f.get(PENDING, 0), f.get(LEASED, 0), f.get(FAILED, 0))


def run_enumeration(
    engine: Engine,
    url: str,
    n: int,
    params: Params,
    client: Client,
    on_progress: Callable[[Progress], None] | None = None,
    max_attempts: int = 3,
    per_worker: int = 4,
    batch: int = BATCH,
    workerless_timeout: float | None = None,
    revive: Callable[[], int] | None = None,
) -> RunResult:
    """Create or resume the run for (n, params) and drive it to the end.

    ``url`` is the database URL the workers use (they open their own engine
    through :class:`packings.service.plugin.DatabasePlugin`).  ``per_worker`` tasks per
    worker thread are kept in flight, of up to ``batch`` expansions each.  After
    ``workerless_timeout`` seconds without a Dask worker the run stops with
    :class:`packings.service.errors.SchedulerError` (None: it waits for workers to join); ``revive`` is called
    every few seconds to replace lost workers (a local cluster's).
    """
    return _Run(
        engine, url, n, params, client, on_progress, max_attempts, per_worker, batch, workerless_timeout, revive
    ).drive()


class _Run(Driver):
    """One coordinator's drive of the run of (n, params) (:func:`run_enumeration`) on the Dask driver
    (:class:`packings.service.driver.Driver`): the run started or resumed, expansions claimed with leases
    and sent in tasks (those whose task was lost, alone), each result consumed (failed expansions released
    to be retried or failed), the heartbeat and the lost workers' tasks counted (:class:`_Departures`)
    beside the drive, and the run finished or abandoned (resumably)."""

    def __init__(
        self,
        engine: Engine,
        url: str,
        n: int,
        params: Params,
        client: Client,
        on_progress: Callable[[Progress], None] | None,
        max_attempts: int,
        per_worker: int,
        batch: int,
        workerless_timeout: float | None,
        revive: Callable[[], int] | None,
    ):
        self.n, self.max_attempts, self.batch = n, max_attempts, batch
        self.Session_ = sessions(engine)
        self.Reader = sessions(engine, readonly=True)
        self.owner = f"{process_name()}:{uuid.uuid4().hex[:8]}"
        self.info = info = store.start_run(self.Session_, n, params, self.owner)
        log.info("run %d (n = %d): %s", info.id, n, "started" if info.created else "resumed")
        if info.recovered:
            log.warning(
                "run %d: %d expansion(s) leased by a coordinator that is gone put back to pending",
                info.id,
                info.recovered,
            )
        plugin = DatabasePlugin(url)
        client.register_plugin(plugin)
        super().__init__(client, f"run {info.id}", per_worker, workerless_timeout, revive, plugin, log)
        self.isolate: set[int] = set()  #: expansions whose task was lost: sent one per task
        self.start = time.perf_counter()
        self.parts: dict[str, list] = {}  #: the expansions of each task in flight, by its key (read by ``departures``)
        self.departures = _Departures(client, info.id, self.parts.get)
        self.shown = Every(
            PROGRESS_SECONDS,
            lambda: on_progress(_progress(self.Reader, info.id)) if on_progress else None,
            PROGRESS_SHARE,
        )

    def reconnected(self) -> None:
        """A restarted scheduler knows no subscription: ask it for its events again."""
        self.departures.subscribe()

    def show(self, force: bool = False) -> None:
        self.shown(force)

    def claim(self, tasks: int) -> list:
        """Up to ``batch`` expansions leased for each task wanted, shared out among those tasks (among
        more, smaller ones when that was all that was pending: :func:`_task_count`); those whose task was
        lost once each alone, first."""
        isolate, batch = self.isolate, self.batch
        claimed = store.claim(self.Session_, self.info.id, self.owner, tasks * batch)
        alone = [[x] for x in claimed if x[0] in isolate]  # each lost once with a task: now on its own
        shared = [x for x in claimed if x[0] not in isolate]
        return alone + _shares(shared, _task_count(len(shared), max(1, tasks - len(alone)), self.capacity, batch))

    def submit(self, part: list):
        """The task of the leased expansions ``part``: one alone goes first (the less it waits on a worker,
        the less a fault of another task hits it).  The key's prefix (Dask's key_split keeps "expand_n12",
        drops "-n12") names the run's n in Dask's own panels (progress, task stream)."""
        eid, token = part[0]
        fut = self.client.submit(
            expand_task,
            part,
            self.plugin.name,
            key=f"expand_n{self.n}-{eid}-{len(part)}-{token}",
            pure=False,
            priority=int(eid in self.isolate),
        )
        fut.expansions = part  # type: ignore[attr-defined]
        self.parts[fut.key] = part
        return fut

    def lost(self, fut, exc: BaseException | None, connection: bool = False) -> None:
        """``fut``'s task was lost to the infrastructure (``exc``; None: cancelled): put its expansions
        back, uncounted, and send each alone from now on; one that was alone already and killed its
        workers again (KilledWorker) counts.  Cancelled because the Client lost the scheduler
        (``connection``), which says nothing about the task: back, uncounted, not sent alone."""
        if connection:
            store.put_back(self.Session_, fut.expansions, "infrastructure fault, retried: the Dask scheduler was lost")
            return
        part = fut.expansions
        why = "task cancelled" if exc is None else error_line(exc)
        if len(part) == 1 and part[0][0] in self.isolate and isinstance(exc, KilledWorker):
            eid, token = part[0]
            status = store.release(
                self.Session_,
                eid,
                token,
                f"lost its workers while running alone: {why}",
                self.max_attempts,
                isolated=True,
            )
            log.error(
                "run %d: expansion %d lost its workers while running alone (%s): %s",
                self.info.id,
                eid,
                why,
                "failed" if status == FAILED else "to be retried",
            )
            return
        # a task whose worker was reported lost was counted then (_Departures): put back, not counted again
        back = store.put_back(
            self.Session_, part, f"infrastructure fault, retried: {why}", retry=fut.key not in self.departures.counted
        )
        self.isolate.update(eid for eid, _ in part)
        log.warning(
            "run %d: a task of %d expansion(s) was lost (%s); %d put back, each to be retried alone",
            self.info.id,
            len(part),
            why,
            back,
        )

    def so_far(self) -> float:
        """The run's time: its earlier coordinators' and this one's."""
        return self.info.seconds + (time.perf_counter() - self.start)

    def failed(self, fut, exc: BaseException) -> None:
        """The expansions of ``fut``'s task that failed (all of them, unless it says which:
        :class:`packings.service.tasks.ExpansionsFailed`) released, to be retried or failed; the run stopped,
        resumably, when the database cannot be written."""
        if isinstance(exc, ExpansionsFailed):
            failed = exc.errors
        else:
            failed = dict.fromkeys((eid for eid, _ in fut.expansions), error_line(exc))
        full = next((line for line in map(cannot_write, failed.values()) if line), None)
        if full is not None:  # no expansion's fault, and no use trying others: stop, resumably
            _try(lambda: store.put_back(self.Session_, fut.expansions, f"database not writable: {full}"))
            raise not_writable(full)
        # an expansion of the task that was written back is no longer leased: release leaves it
        for eid, token in fut.expansions:
            if eid in failed:
                status = store.release(self.Session_, eid, token, failed[eid], self.max_attempts)
                log.warning(
                    "run %d: expansion %d failed (%s): %s",
                    self.info.id,
                    eid,
                    summary(failed[eid]),
                    "given up" if status == FAILED else "to be retried",
                )

    def consume(self, fut) -> None:
        """One task's result (:meth:`packings.service.driver.Driver.consume`), after the workers reported
        lost since the last one are counted."""
        self.parts.pop(fut.key, None)
        self.departures.count(self.Session_)
        super().consume(fut)

    def drive(self) -> RunResult:
        """The run driven to its end, its heartbeat beating meanwhile; on any exception (an interrupt too)
        the run is abandoned (:meth:`abandon`) and the exception raised."""
        self.beat = _Heartbeat(self.Session_, self.info.id, self.owner, self.so_far)
        return super().drive()

    def drained(self) -> None:
        self.departures.count(self.Session_)
        self.shown(force=True)

    def abandon(self, e: BaseException) -> None:
        """The run's leases put back (if the database cannot take this either, the next coordinator puts
        them back); a database that cannot be written raised as :func:`not_writable`'s one line."""
        _try(lambda: store.abandon(self.Session_, self.info.id, self.owner, self.so_far()))
        full = None if isinstance(e, StorageError) else cannot_write(str(e))
        if full is not None:  # the coordinator's own write failed so
            raise not_writable(full) from None

    def stop(self) -> None:
        """The heartbeat, the watchdog and the subscription to the scheduler's events stopped."""
        self.beat.stop()
        super().stop()
        self.departures.close()

    def finish(self) -> RunResult:
        """The run marked complete (or incomplete, if some expansion failed) and its result."""
        info, Session_ = self.info, self.Session_
        seconds = time.perf_counter() - self.start
        status = store.finish_run(Session_, info.id, self.owner, self.so_far())
        log.info("run %d (n = %d): %s after %.1f s", info.id, self.n, status, seconds)
        with self.Reader() as s:
            by_contacts = queries.run_counts(s, info.id)
            diagnostics = queries.run_diagnostics(s, info.id)
            errors = [
                f"expansion {i}: {summary(e or '')}"
                for i, e in s.execute(
                    select(ExpansionRow.id, ExpansionRow.error).where(
                        ExpansionRow.run_id == info.id, ExpansionRow.status == FAILED
                    )
                )
            ]
        return RunResult(
            info.id, self.n, status, by_contacts, diagnostics, seconds, not info.created, errors, info.seconds + seconds
        )
