"""The coordinator: drives one run from the frontier in the database.

It claims pending expansions in batches sized to the workers, submits them as
Dask tasks of up to ``batch`` expansions each (fewer, while a claim takes all
that is pending: at the start and the end of a run), consumes results as they
complete and claims more, until nothing is pending or leased.  A task writes
its expansions back in one transaction, each guarded by its lease token.

Failures are of two kinds:

* an expansion that fails (``expand`` or its write-back raised) is put back to
  pending and retried, at most ``max_attempts`` times in all, then marked
  failed with its error's traceback;
* a task lost to the infrastructure (its worker died, :data:`INFRASTRUCTURE`,
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
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Callable

from distributed import Client, as_completed
from distributed.client import FutureCancelledError
from distributed.comm.core import CommClosedError
from distributed.scheduler import KilledWorker
from sqlalchemy import Engine, select

from packings.service import queries, store
from packings.service.db import sessions
from packings.service.errors import SchedulerError, StorageError
from packings.service.models import DONE, FAILED, LEASED, PENDING, ExpansionRow
from packings.service.owners import process_name
from packings.service.plugin import DatabasePlugin
from packings.service.tasks import ExpansionsFailed, error_line, expand_task, summary
from packings.workers.params import Params

log = logging.getLogger(__name__)

#: a task that raised one of these was lost with its worker or its connection: no fault of its expansions
INFRASTRUCTURE = (KilledWorker, CommClosedError, FutureCancelledError)
#: why Dask's Client cancels every future it holds when it loses its scheduler, which it then tries to reach
#: again (FutureCancelledError.reason)
CONNECTION_LOST = "scheduler-connection-lost"
RECONNECT_MARGIN = 30.0  #: how long past the Client's own reconnection window the coordinator waits for it
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
CAPACITY_SECONDS = 2.0  #: how often the number of worker threads is asked again
WATCH_SECONDS = 2.0  #: how often the watchdog asks whether any worker is left
PROGRESS_SECONDS = 0.25  #: how often progress is read from the database and shown
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


class _Every:
    """``f()``'s value, recomputed at most every ``seconds`` (or when forced): the coordinator
    asks for the worker threads and shows progress after every result, and neither needs to be
    fresher than this."""

    def __init__(self, seconds: float, f: Callable):
        self.seconds, self.f = seconds, f
        self.at, self.value = -float("inf"), None

    def __call__(self, force: bool = False):
        now = time.monotonic()
        if force or now - self.at >= self.seconds:
            self.at, self.value = now, self.f()
        return self.value


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


class _Watchdog(threading.Thread):
    """Watches the Dask workers every WATCH_SECONDS.  It logs a line for the workers that left since
    (a killed process, a Slurm job cancelled or past its walltime, a machine lost) and calls
    ``revive()`` (a local cluster's: replace the workers its nannies could not restart; Slurm's: replace
    the jobs lost).  While there is no worker it logs a warning every minute; after ``timeout`` seconds
    without one it sets :attr:`stalled` and cancels the tasks in flight (``cancel()``), so that the
    coordinator stops, resumably, rather than wait for ever."""

    def __init__(
        self,
        client: Client,
        run_id: int,
        timeout: float | None,
        cancel: Callable[[], None],
        revive: Callable[[], int] | None = None,
    ):
        super().__init__(name="packings-watchdog", daemon=True)
        self.client, self.run_id, self.timeout, self.cancel, self.revive = client, run_id, timeout, cancel, revive
        self.stalled = False
        self.stopped = threading.Event()
        self.start()

    def run(self) -> None:
        since = warned = None
        seen: set[str] = set()  #: the workers there at the last look
        ever = False  #: whether any worker has been seen
        while not self.stopped.wait(WATCH_SECONDS):
            try:
                if self.revive is not None:
                    self.revive()
                present = set(self.client.nthreads())
            except Exception:  # noqa: BLE001 - the scheduler itself is away: Dask reconnects or fails the tasks
                continue
            left = seen - present
            if left:
                log.warning(
                    "run %d: %d Dask worker(s) left (%s); %d remain",
                    self.run_id,
                    len(left),
                    ", ".join(sorted(left)[:4]) + (", ..." if len(left) > 4 else ""),
                    len(present),
                )
            seen = present
            ever = ever or bool(present)
            workers = len(present)
            now = time.monotonic()
            if workers:
                since = warned = None
                continue
            since = since or now
            # none has joined yet (Slurm's jobs may wait in its queue): said after a minute, not at once
            first = warned is None and (ever or now - since >= 60)
            if first or (warned is not None and now - warned >= 60):
                log.warning(
                    "run %d: no Dask worker for %.0f s%s",
                    self.run_id,
                    now - since,
                    "" if ever else " (none has joined yet)",
                )
                warned = now
            if self.timeout is not None and now - since >= self.timeout:
                self.stalled = True
                self.cancel()
                return

    def stop(self) -> None:
        self.stopped.set()


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


def cancel_reason(fut) -> str:
    """Why Dask cancelled ``fut``: :data:`CONNECTION_LOST` when its Client lost the scheduler, "unknown"
    if it does not say (the reason Dask records on the future's state)."""
    exc = getattr(getattr(fut, "_state", None), "exception", None)
    return str(getattr(exc, "reason", None) or "unknown")


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


class _Run:
    """One coordinator's drive of the run of (n, params) (:func:`run_enumeration`): the run started or
    resumed, the tasks in flight and the expansions sent alone, the scheduler reached again when it is
    lost, each result consumed, and the run finished or abandoned (resumably)."""

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
        self.n, self.client, self.max_attempts = n, client, max_attempts
        self.per_worker, self.batch, self.workerless_timeout = per_worker, batch, workerless_timeout
        self.revive = revive  #: called by the watchdog to replace lost workers
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
        self.isolate: set[int] = set()  #: expansions whose task was lost: sent one per task
        self.plugin = DatabasePlugin(url)
        client.register_plugin(self.plugin)
        self.start = time.perf_counter()
        self.ac = as_completed()
        self.flight: set = set()  #: the tasks in flight (the watchdog cancels them)
        self.parts: dict[str, list] = {}  #: the expansions of each task in flight, by its key (read by ``departures``)
        self.departures = _Departures(client, info.id, self.parts.get)
        self.threads = _Every(CAPACITY_SECONDS, lambda: sum(client.nthreads().values()) or 1)
        self.shown = _Every(
            PROGRESS_SECONDS, lambda: on_progress(_progress(self.Reader, info.id)) if on_progress else None
        )

    def reconnect(self) -> None:
        """The Client lost its scheduler (an existing cluster's, gone or restarting): wait while it tries
        to reach it again, for its own window (:data:`packings.service.dask_cluster.RECONNECT_SECONDS`), then
        register the database plugin again (a restarted scheduler knows none, and gives it to the
        workers that join it); if it cannot, stop, resumably."""
        since = time.monotonic()
        log.warning("run %d: lost the Dask scheduler; trying to reach it again for %.0f s", self.info.id, self.window())
        while True:
            self.gone_since(since)
            if self.client.status == "running":
                try:
                    self.client.register_plugin(self.plugin)
                    self.departures.subscribe()
                    break
                except OSError:  # lost again as it was asked (CommClosedError is one)
                    pass
            time.sleep(0.2)
        log.warning("run %d: reached the Dask scheduler again after %.1f s", self.info.id, time.monotonic() - since)

    def window(self) -> float:
        """How long the Client tries to reach its scheduler again once it lost it."""
        return float(getattr(self.client, "_timeout", 0) or 0)

    def gone_since(self, since: float) -> None:
        """Stop, resumably, if the scheduler has been out of reach since ``since`` for longer than the
        Client tries to reach it again (or the Client gave up)."""
        waited = time.monotonic() - since
        if self.client.status in ("closing", "closed") or waited > self.window() + RECONNECT_MARGIN:
            raise SchedulerError(
                f"lost the Dask scheduler and could not reach it again in {waited:.0f} s; "
                "run the same command to resume"
            )

    def capacity_now(self) -> int:
        """Tasks to keep in flight.  The connection can break as the scheduler is asked, before the Client
        has noticed that it lost it (its status still "running"): then reach it again (the plugin given
        again, as to a restarted scheduler) and ask again."""
        since = time.monotonic()
        if self.client.status != "running":
            self.reconnect()
        while True:
            try:
                return self.per_worker * self.threads()
            except OSError:  # CommClosedError is one
                self.gone_since(since)
                time.sleep(0.2)
                self.reconnect()

    def fill(self, force: bool = False) -> None:
        """Keep up to ``per_worker`` tasks per worker thread in flight: claim once at most half of them
        are left (one claim transaction per few results rather than per result), up to ``batch``
        expansions for each task wanted, and share what was claimed out among those tasks (among more,
        smaller ones when that was all that was pending: :func:`_task_count`)."""
        capacity = self.capacity_now()
        flight, isolate, batch = self.flight, self.isolate, self.batch
        if not force and len(flight) > capacity // 2:
            return
        tasks = capacity - len(flight)
        claimed = store.claim(self.Session_, self.info.id, self.owner, tasks * batch)
        alone = [[x] for x in claimed if x[0] in isolate]  # each lost once with a task: now on its own
        shared = [x for x in claimed if x[0] not in isolate]
        for part in alone + _shares(shared, _task_count(len(shared), max(1, tasks - len(alone)), capacity, batch)):
            eid, token = part[0]
            # one alone goes first: the less it waits on a worker, the less a fault of another task hits it.
            # The key's prefix (Dask's key_split keeps "expand_n12", drops "-n12") names the run's n in
            # Dask's own panels (progress, task stream)
            fut = self.client.submit(
                expand_task,
                part,
                self.plugin.name,
                key=f"expand_n{self.n}-{eid}-{len(part)}-{token}",
                pure=False,
                priority=int(eid in isolate),
            )
            fut.expansions = part  # type: ignore[attr-defined]
            self.parts[fut.key] = part
            self.ac.add(fut)
            flight.add(fut)

    def lost(self, fut, exc: BaseException | None) -> None:
        """``fut``'s task was lost to the infrastructure (``exc``; None: cancelled): put its expansions
        back, uncounted, and send each alone from now on; one that was alone already and killed its
        workers again (KilledWorker) counts."""
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

    def failures(self, fut) -> dict[int, str]:
        """The expansions of ``fut``'s task that failed, each with its error (none when it was lost to the
        infrastructure: then they were put back here)."""
        if fut.status == "cancelled" and cancel_reason(fut) == CONNECTION_LOST:
            # the Client lost the scheduler, which says nothing about the task: back, uncounted
            store.put_back(self.Session_, fut.expansions, "infrastructure fault, retried: the Dask scheduler was lost")
        elif fut.status == "cancelled":  # the scheduler forgot it (restarted, or lost its state)
            self.lost(fut, None)
        elif fut.status == "error":
            exc = fut.exception()
            if isinstance(exc, INFRASTRUCTURE):
                self.lost(fut, exc)
            elif isinstance(exc, ExpansionsFailed):
                return exc.errors
            else:
                return dict.fromkeys((eid for eid, _ in fut.expansions), error_line(exc))
        return {}

    def consume(self, fut) -> None:
        """One task's result: its failed expansions released (retried or failed), or the run stopped,
        resumably, when the database cannot be written or no worker is left."""
        self.flight.discard(fut)
        self.parts.pop(fut.key, None)
        self.departures.count(self.Session_)
        failed = self.failures(fut)
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
        fut.release()
        if self.watchdog.stalled:
            raise SchedulerError(
                f"no Dask worker for {self.workerless_timeout:.0f} s (the local cluster could "
                "not start them again); run the same command to resume"
            )

    def drive(self) -> RunResult:
        """Submit, consume and claim more until nothing is in flight; on any exception (an interrupt
        too) the run is abandoned, its leases put back, and the exception raised (a database that cannot
        be written as :func:`not_writable`'s one line)."""
        self.beat = _Heartbeat(self.Session_, self.info.id, self.owner, self.so_far)
        self.watchdog = _Watchdog(
            self.client,
            self.info.id,
            self.workerless_timeout,
            lambda: self.client.cancel(list(self.flight.copy())),
            self.revive,
        )
        try:
            self.fill(force=True)
            self.shown(force=True)
            while self.flight:
                for fut in self.ac:
                    self.consume(fut)
                    self.fill()
                    self.shown()
                self.fill(force=True)
            self.departures.count(self.Session_)
            self.shown(force=True)
        except BaseException:
            self.stop()
            # if the database cannot take this either, the next coordinator puts the leases back
            _try(lambda: store.abandon(self.Session_, self.info.id, self.owner, self.so_far()))
            e = sys.exc_info()[1]
            full = None if isinstance(e, StorageError) else cannot_write(str(e))
            if full is not None:  # the coordinator's own write failed so
                raise not_writable(full) from None
            raise
        self.stop()
        return self.finish()

    def stop(self) -> None:
        """The heartbeat, the watchdog and the subscription to the scheduler's events stopped."""
        self.beat.stop()
        self.watchdog.stop()
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
