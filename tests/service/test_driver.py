"""packings.service.driver: the watchdog's count of time without a Dask worker."""

import threading
import time
import types

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


def test_every_keeps_a_slow_read_to_its_share_of_the_time(monkeypatch):
    """A read that takes 0.1 s with a share of 5 % is made again only 2 s after it started, not every 0.25 s;
    once it is fast again, every 0.25 s; without a share, every 0.25 s whatever it costs; forced, at once."""
    now = [100.0]
    monkeypatch.setattr(driver, "time", types.SimpleNamespace(monotonic=lambda: now[0]))
    cost, calls = [0.1], []

    def read():
        calls.append(now[0])
        now[0] += cost[0]
        return len(calls)

    def every_tick(e, seconds: float) -> list:
        """Call ``e`` at each step of 0.05 s for ``seconds``: the values it gave."""
        seen = []
        for _ in range(round(seconds / 0.05)):
            seen.append(e())
            now[0] += 0.05
        return seen

    slow = driver.Every(0.25, read, share=0.05)
    every_tick(slow, 4.0)
    assert [round(t - calls[0], 2) for t in calls] == [0.0, 2.0, 4.0]  # not every 0.25 s: 16 calls
    cost[0] = 0.0
    calls.clear()
    every_tick(slow, 3.0)
    gaps = [round(b - a, 2) for a, b in zip(calls, calls[1:])]
    assert gaps and gaps[0] <= 2.0 and all(0.25 <= g <= 0.3 for g in gaps[1:])  # the next tick past 0.25 s
    made = len(calls)
    slow(force=True)
    assert len(calls) == made + 1  # at once, however recent the last
    calls.clear()
    cost[0] = 0.1
    plain = driver.Every(0.25, read)
    every_tick(plain, 1.0)
    assert len(calls) >= 3 and all(round(b - a, 2) <= 0.3 for a, b in zip(calls, calls[1:]))
