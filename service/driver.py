"""The Dask driver every kind of the service's tasks runs on: what keeps work in flight on a cluster that may
lose workers, or its scheduler, under it.

:class:`Driver` keeps up to ``per_worker`` tasks per worker thread in flight (the threads asked again every
:data:`CAPACITY_SECONDS`), consumes each task as it completes and submits more, until its subclass has
nothing more to submit and nothing is in flight.  Each finished task is sorted into one of three:

* succeeded;
* lost to the infrastructure, which says nothing about its work: it raised one of :func:`infrastructure`
  (its worker died, :class:`~distributed.scheduler.KilledWorker`; its connection closed), or it was
  cancelled, by the Client when it lost its scheduler (:data:`CONNECTION_LOST`) or by the scheduler that
  forgot it;
* failed with an error of its own.

When the Client loses its scheduler the driver waits while it tries to reach it again, for its window
and :data:`RECONNECT_MARGIN` more, gives the scheduler the database plugin again (a restarted one knows
none) and goes on; else it stops with :class:`packings.service.errors.SchedulerError`.  A watchdog thread
(:class:`_Watchdog`) logs the workers that leave, calls ``revive()`` to replace them (a local cluster's,
Slurm's jobs), and after ``workerless_timeout`` seconds without any worker cancels the tasks in flight,
which stops the driver with SchedulerError rather than wait for ever.

What to submit and what a result means are the subclass's: :meth:`Driver.claim`, :meth:`Driver.submit`,
:meth:`Driver.succeeded`, :meth:`Driver.lost`, :meth:`Driver.failed`, :meth:`Driver.abandon` and
:meth:`Driver.finish`.  There are two: a run's expansions, leased in the database
(:class:`packings.service.coordinator._Run`), and a catalysis pass's batches of parents, retried in memory
(:class:`packings.service.catalysis._Pass`).

Dask is imported when a driver is made, not with this module: :mod:`packings.service.catalysis` imports
it, and a pass decided in one process needs no Dask.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from typing import Callable

from packings.service.errors import SchedulerError

log = logging.getLogger(__name__)

#: why Dask's Client cancels every future it holds when it loses its scheduler, which it then tries to reach
#: again (FutureCancelledError.reason)
CONNECTION_LOST = "scheduler-connection-lost"
RECONNECT_MARGIN = 30.0  #: how long past the Client's own reconnection window the driver waits for it
CAPACITY_SECONDS = 2.0  #: how often the number of worker threads is asked again
WATCH_SECONDS = 2.0  #: how often the watchdog asks whether any worker is left


@functools.cache
def infrastructure() -> tuple[type[BaseException], ...]:
    """The exceptions of a task lost with its worker or its connection: no fault of its work."""
    from distributed.client import FutureCancelledError
    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    return (KilledWorker, CommClosedError, FutureCancelledError)


def cancel_reason(fut) -> str:
    """Why Dask cancelled ``fut``: :data:`CONNECTION_LOST` when its Client lost the scheduler, "unknown"
    if it does not say (the reason Dask records on the future's state)."""
    exc = getattr(getattr(fut, "_state", None), "exception", None)
    return str(getattr(exc, "reason", None) or "unknown")


class Every:
    """``f()``'s value, recomputed at most every ``seconds`` (or when forced): the driver asks for the
    worker threads and shows progress after every result, and neither needs to be fresher than this.
    With ``share``, also at most that share of the time: after a call that took t seconds the next waits
    t / share at least, so that a read whose cost grows with the run (progress counts every expansion of
    it: tens of milliseconds with a million) keeps to its share of the coordinator's time and the database's."""

    def __init__(self, seconds: float, f: Callable, share: float | None = None):
        self.seconds, self.f, self.share = seconds, f, share
        self.at, self.value = -float("inf"), None
        self.wait = seconds  #: until the next call: ``seconds``, or longer after a slow one (``share``)

    def __call__(self, force: bool = False):
        now = time.monotonic()
        if force or now - self.at >= self.wait:
            self.value = self.f()
            took = time.monotonic() - now
            self.at = now
            self.wait = self.seconds if self.share is None else max(self.seconds, took / self.share)
        return self.value


class _Watchdog(threading.Thread):
    """Watches the Dask workers every WATCH_SECONDS.  It logs a line for the workers that left since
    (a killed process, a Slurm job cancelled or past its walltime, a machine lost) and calls
    ``revive()`` (a local cluster's: replace the workers its nannies could not restart; Slurm's: replace
    the jobs lost).  While there is no worker it logs a warning every minute; after ``timeout`` seconds
    without one it sets :attr:`stalled` and cancels the tasks in flight (``cancel()``), so that the
    driver stops rather than wait for ever.  A worker that joined between two looks and was gone again at
    the second (the scheduler's ``add-worker`` events say so) counts as one there: on a loaded machine whose
    workers are killed faster than they are started, none may be there at any look while they keep coming,
    and the run keeps going.  Its lines begin with ``label`` (e.g. "run 5")."""

    def __init__(
        self,
        client,
        label: str,
        timeout: float | None,
        cancel: Callable[[], None],
        revive: Callable[[], int] | None = None,
        logger: logging.Logger = log,
    ):
        super().__init__(name="packings-watchdog", daemon=True)
        self.client, self.label, self.timeout, self.cancel, self.revive = client, label, timeout, cancel, revive
        self.log = logger
        self.stalled = False
        self.stopped = threading.Event()
        self.start()

    def last_arrival(self) -> float | None:
        """When a worker last joined, by the scheduler's clock (its events on the topic "all"); None if it
        does not say."""
        try:
            events = self.client.get_events("all")
        except Exception:  # noqa: BLE001 - the scheduler itself is away: the next look asks again
            return None
        return max(
            (t for t, msg in events if isinstance(msg, dict) and msg.get("action") == "add-worker"), default=None
        )

    def run(self) -> None:
        since = warned = None
        seen: set[str] = set()  #: the workers there at the last look
        ever = False  #: whether any worker has been seen
        arrival = None  #: the last worker's arrival, as asked at the last look without a worker
        while not self.stopped.wait(WATCH_SECONDS):
            try:
                if self.revive is not None:
                    self.revive()
                present = set(self.client.nthreads())
            except Exception:  # noqa: BLE001 - the scheduler itself is away: Dask reconnects or fails the tasks
                continue
            left = seen - present
            if left:
                self.log.warning(
                    "%s: %d Dask worker(s) left (%s); %d remain",
                    self.label,
                    len(left),
                    ", ".join(sorted(left)[:4]) + (", ..." if len(left) > 4 else ""),
                    len(present),
                )
            seen = present
            ever = ever or bool(present)
            now = time.monotonic()
            if present:
                since = warned = arrival = None
                continue
            last, arrival = arrival, self.last_arrival()
            if last is not None and arrival is not None and arrival > last:  # one came and went since the last look
                since, warned, ever = None, None, True
                continue
            since = since or now
            # none has joined yet (Slurm's jobs may wait in its queue): said after a minute, not at once
            first = warned is None and (ever or now - since >= 60)
            if first or (warned is not None and now - warned >= 60):
                self.log.warning(
                    "%s: no Dask worker for %.0f s%s", self.label, now - since, "" if ever else " (none has joined yet)"
                )
                warned = now
            if self.timeout is not None and now - since >= self.timeout:
                self.stalled = True
                self.cancel()
                return

    def stop(self) -> None:
        self.stopped.set()


class Driver:
    """Drives tasks on the Dask ``client`` (module doc): ``per_worker`` tasks per worker thread in flight,
    the scheduler reached again when it is lost (and ``plugin``, if given, registered with it again), a
    watchdog that stops the drive after ``workerless_timeout`` seconds without a worker (None: it waits)
    and calls ``revive`` to replace lost workers.  Log lines begin with ``label`` and go to ``logger``;
    ``resume`` ends the messages of the errors that stop the drive (what to do next)."""

    resume = "run the same command to resume"

    def __init__(
        self,
        client,
        label: str,
        per_worker: int,
        workerless_timeout: float | None = None,
        revive: Callable[[], int] | None = None,
        plugin=None,
        logger: logging.Logger = log,
    ):
        from distributed import as_completed

        self.client, self.label, self.per_worker = client, label, per_worker
        self.workerless_timeout, self.revive, self.plugin, self.log = workerless_timeout, revive, plugin, logger
        self.ac = as_completed()
        self.flight: set = set()  #: the tasks in flight (the watchdog cancels them)
        self.capacity = 0  #: the tasks to keep in flight, as the last fill found it
        self.threads = Every(CAPACITY_SECONDS, lambda: sum(client.nthreads().values()) or 1)
        self.watchdog: _Watchdog | None = None

    # ------------------------------------------------------------------ what a subclass supplies

    def claim(self, tasks: int) -> list:
        """The work of up to ``tasks`` new tasks (fewer, or none, when there is less), one item each."""
        raise NotImplementedError

    def submit(self, item):
        """``item``'s task submitted: its future."""
        raise NotImplementedError

    def succeeded(self, fut) -> None:
        """``fut``'s task ran to its end."""

    def lost(self, fut, exc: BaseException | None, connection: bool = False) -> None:
        """``fut``'s task was lost to the infrastructure: ``exc`` (one of :func:`infrastructure`), or
        cancelled (None), because the Client lost its scheduler (``connection``) or by the scheduler."""
        raise NotImplementedError

    def failed(self, fut, exc: BaseException) -> None:
        """``fut``'s task raised ``exc``, an error of its own; may raise to stop the drive."""
        raise NotImplementedError

    def reconnected(self) -> None:
        """The scheduler was reached again (and given the plugin): what else it must be told again."""

    def show(self, force: bool = False) -> None:
        """Progress shown, after each result (``force``: now)."""

    def drained(self) -> None:
        """Nothing is in flight and nothing more to claim: the last word before :meth:`finish`."""

    def abandon(self, e: BaseException) -> None:
        """The drive stops on ``e`` (the watchdog stopped already); may raise another exception instead."""

    def finish(self):
        """The drive ran to its end (the watchdog stopped): its result."""

    # ------------------------------------------------------------------ the drive

    def drive(self):
        """Submit, consume and claim more until nothing is in flight, then :meth:`finish`; on any exception
        (an interrupt too) the watchdog is stopped, :meth:`abandon` called, and the exception raised."""
        self.watchdog = _Watchdog(
            self.client, self.label, self.workerless_timeout, self.cancel_flight, self.revive, self.log
        )
        try:
            self.fill(force=True)
            self.show(force=True)
            while self.flight:
                for fut in self.ac:
                    self.consume(fut)
                    self.fill()
                    self.show()
                self.fill(force=True)
            self.drained()
        except BaseException as e:
            self.stop()
            self.abandon(e)
            raise
        self.stop()
        return self.finish()

    def stop(self) -> None:
        """The watchdog stopped (and whatever else a subclass runs beside the drive)."""
        if self.watchdog is not None:
            self.watchdog.stop()

    def cancel_flight(self) -> None:
        """Cancel the tasks in flight (the watchdog, once no worker is left): they come back cancelled."""
        self.client.cancel(list(self.flight.copy()))

    def fill(self, force: bool = False) -> None:
        """Keep up to ``per_worker`` tasks per worker thread in flight: claim once at most half of them are
        left (one claim per few results rather than per result), and submit what was claimed."""
        self.capacity = capacity = self.capacity_now()
        if not force and len(self.flight) > capacity // 2:
            return
        for item in self.claim(capacity - len(self.flight)):
            fut = self.submit(item)
            self.ac.add(fut)
            self.flight.add(fut)

    def consume(self, fut) -> None:
        """One task's end, sorted (:meth:`settle`) and released; the drive stopped with SchedulerError
        once the watchdog found no worker for ``workerless_timeout`` seconds."""
        self.flight.discard(fut)
        self.settle(fut)
        fut.release()
        if self.watchdog is not None and self.watchdog.stalled:
            raise SchedulerError(
                f"no Dask worker for {self.workerless_timeout:.0f} s (the local cluster could "
                f"not start them again); {self.resume}"
            )

    def settle(self, fut) -> None:
        """Call the hook for how ``fut``'s task ended: :meth:`succeeded`, :meth:`lost` or :meth:`failed`."""
        if fut.status == "cancelled":
            self.lost(fut, None, connection=cancel_reason(fut) == CONNECTION_LOST)
        elif fut.status == "error":
            exc = fut.exception()
            if isinstance(exc, infrastructure()):
                self.lost(fut, exc)
            else:
                self.failed(fut, exc)
        else:
            self.succeeded(fut)

    # ------------------------------------------------------------------ the scheduler lost and reached again

    def window(self) -> float:
        """How long the Client tries to reach its scheduler again once it lost it."""
        return float(getattr(self.client, "_timeout", 0) or 0)

    def gone_since(self, since: float) -> None:
        """Stop if the scheduler has been out of reach since ``since`` for longer than the Client tries to
        reach it again (or the Client gave up)."""
        waited = time.monotonic() - since
        if self.client.status in ("closing", "closed") or waited > self.window() + RECONNECT_MARGIN:
            raise SchedulerError(
                f"lost the Dask scheduler and could not reach it again in {waited:.0f} s; {self.resume}"
            )

    def reconnect(self) -> None:
        """The Client lost its scheduler (an existing cluster's, gone or restarting): wait while it tries
        to reach it again, for its own window (:data:`packings.service.dask_cluster.RECONNECT_SECONDS`), then
        register the database plugin again (a restarted scheduler knows none, and gives it to the
        workers that join it) and :meth:`reconnected`; if it cannot, stop (:meth:`gone_since`)."""
        since = time.monotonic()
        self.log.warning("%s: lost the Dask scheduler; trying to reach it again for %.0f s", self.label, self.window())
        while True:
            self.gone_since(since)
            if self.client.status == "running":
                try:
                    if self.plugin is not None:
                        self.client.register_plugin(self.plugin)
                    self.reconnected()
                    break
                except OSError:  # lost again as it was asked (CommClosedError is one)
                    pass
            time.sleep(0.2)
        self.log.warning("%s: reached the Dask scheduler again after %.1f s", self.label, time.monotonic() - since)

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
