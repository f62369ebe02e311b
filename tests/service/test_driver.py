"""packings.service.driver: the watchdog's count of time without a Dask worker."""

import threading
import time

from packings.service import driver
from tests.helpers import wait_for


class _Scheduler:
    """A Client's answers to the watchdog: never a worker at a look, and the scheduler's events on the topic
    "all", to which each call of :meth:`arrive` adds one worker that joined (and is gone again)."""

    def __init__(self):
        self.events: list[tuple[float, dict]] = [(1.0, {"action": "add-worker", "worker": "tcp://a:1"})]
        self.lock = threading.Lock()

    def nthreads(self) -> dict:
        return {}

    def get_events(self, topic: str):
        assert topic == "all"
        with self.lock:
            return tuple(self.events)

    def arrive(self) -> None:
        with self.lock:
            t = self.events[-1][0] + 1.0
            self.events += [(t, {"action": "add-worker", "worker": f"tcp://a:{int(t)}"}), (t, {"action": "other"})]


def test_workers_that_keep_joining_between_looks_are_not_a_cluster_without_workers(monkeypatch):
    """Workers killed faster than they are started, so that none is there at any look: while new ones keep
    joining the watchdog does not stop the drive; once none joins for ``timeout`` seconds it does."""
    monkeypatch.setattr(driver, "WATCH_SECONDS", 0.02)
    scheduler, cancelled = _Scheduler(), threading.Event()
    dog = driver._Watchdog(scheduler, "run 1", 0.3, cancelled.set)
    try:
        end = time.monotonic() + 1.5  # five timeouts
        while time.monotonic() < end:
            scheduler.arrive()
            time.sleep(0.05)
        assert not dog.stalled and not cancelled.is_set()
        wait_for(cancelled.is_set, timeout=10, what="the watchdog's stop once no worker joins")
        assert dog.stalled
    finally:
        dog.stop()
