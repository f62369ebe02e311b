"""The packings page of the Dask dashboard, fetched over HTTP during real runs."""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
import subprocess
import sys
import threading

import pytest
from sqlalchemy import text

from benchmarks.screenshot import render
from packings.service import dashboard
from packings.service.dashboard import Watcher
from packings.service.db import make_engine
from tests.helpers import done_count, fetch, fill_database, free_port, packings, wait_for

CHROMIUM = shutil.which("chromium")


def _database_now(url: str) -> dict:
    engine = make_engine(url)
    with engine.connect() as c:
        done = c.execute(text("SELECT count(*) FROM expansions WHERE status = 'done'")).scalar()
        clusters = c.execute(text("SELECT count(*) FROM expansions")).scalar()
    engine.dispose()
    return {"done": done, "clusters": clusters}


def test_the_page_shows_the_run_as_the_database_has_it(db_url):
    port = free_port()
    # n = 11, not 10: n = 10's run ends about two seconds after it starts, before the page is read
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "packings.service.cli",
            "enumerate",
            "11",
            "--db",
            db_url,
            "--workers",
            "2",
            "--dashboard-address",
            f"127.0.0.1:{port}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )

    def page_with_a_rate():
        """(database before, status, snapshot, database after) of a read of the page that had seen 20
        expansions done and a rate: two of the page's reads with expansions done between them."""
        before = _database_now(db_url)
        status, body = fetch(f"http://127.0.0.1:{port}/packings.json")
        after = _database_now(db_url)
        snap = json.loads(body)
        if snap.get("rate", 0) > 0 and snap.get("frontier", {}).get("done", 0) >= 20:
            return before, status, snap, after
        return None

    try:
        wait_for(lambda: done_count(db_url) >= 20, proc)
        before, status, snap, after = wait_for(
            page_with_a_rate, proc, timeout=600, interval=0.5, what="the page shows 20 expansions done and a rate"
        )
        page_status, page = fetch(f"http://127.0.0.1:{port}/packings")
        # Dask's own page renders its plots on the first request: seconds where the cores are shared
        _, dask_status = fetch(f"http://127.0.0.1:{port}/status", timeout=60.0)
        out, err = proc.communicate(timeout=900)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert status == 200 and (snap["run"], snap["n"], snap["status"]) == (1, 11, "running")
    # read within a second or two before the fetch: between what the database had before and after it
    assert snap["frontier"]["done"] <= after["done"] and snap["clusters"] <= after["clusters"]
    assert snap["frontier"]["done"] >= 20 and snap["clusters"] >= 20
    assert sum(snap["frontier"].values()) == snap["clusters"] == sum(snap["by_contacts"].values())
    assert snap["rate"] > 0 and snap["eta_seconds"] is not None and snap["failed"] == []
    assert (snap["paper"], snap["min_contacts"]) == (1659, None)  # the paper's count, to compare
    assert sum(w["done"] for w in snap["workers"]) == snap["frontier"]["done"] and len(snap["workers"]) <= 2
    assert before["done"] >= 20
    assert page_status == 200 and "Dask Diagnostic UI" in page and "bokeh" in page  # the Bokeh document's page
    assert 'href="packings"' in dask_status  # in the dashboard's navigation bar
    assert f"dashboard http://127.0.0.1:{port}/packings" in err


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (Debian: apt-get install chromium)")
def test_the_page_draws_in_a_browser(sqlite_url):
    """Headless Chromium draws the page during a run: the run's numbers, and no script error.  n = 11, which
    lasts long enough (n = 10 can end, and its dashboard with it, before the browser has loaded the page)."""
    port = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "packings.service.cli",
            "enumerate",
            "11",
            "--db",
            sqlite_url,
            "--workers",
            "2",
            "--quiet",
            "--dashboard-address",
            f"127.0.0.1:{port}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for(lambda: done_count(sqlite_url) >= 5, proc)
        drawn = render(f"http://127.0.0.1:{port}/packings", wait=120.0, until="expansions done")
        proc.communicate(timeout=900)
    finally:
        proc.kill()
    assert drawn["errors"] == [] and "run 1 (n = 11), running" in drawn["text"], drawn["text"][-600:]
    assert "clusters found" in drawn["text"] and "expansions done" in drawn["text"]
    assert "(the paper has 1,659; the paths alone miss some: a glued pass follows them" in drawn["text"], drawn["text"][
        -600:
    ]
    assert drawn["png"].startswith(b"\x89PNG")


def test_a_taken_dashboard_port_is_said(sqlite_url):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = packings("enumerate", "7", "--db", sqlite_url, "--workers", "1", "--dashboard-address", f"127.0.0.1:{port}")
    assert r.returncode == 0, r.stderr
    assert f"packings: dashboard port {port} is taken; serving it on " in r.stderr
    assert "UserWarning" not in r.stderr


class _Stop(Exception):
    pass


class _Clock:
    """The dashboard's clock made virtual (it stands for the ``time`` module there): sleeping moves it on at
    once, by what was asked; ``on_sleep`` is called in every pause (somebody looking at the page), and after
    ``stop_after`` pauses a sleep raises _Stop, which ends a watcher run in the test's own thread."""

    def __init__(self, on_sleep=None, stop_after: int | None = None):
        self.now = 1000.0
        self.pauses: list[float] = []
        self.on_sleep, self.stop_after = on_sleep, stop_after

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.pauses.append(seconds)
        self.now += seconds
        if self.on_sleep is not None:
            self.on_sleep()
        if self.stop_after is not None and len(self.pauses) >= self.stop_after:
            raise _Stop


class _Looked(threading.Event):
    """The watcher's event that somebody looked, telling whether the watcher waits on it (nobody looks)."""

    waiting = False

    def wait(self, timeout=None):
        self.waiting = True
        try:
            return super().wait(timeout)
        finally:
            self.waiting = False


class _Slow(Watcher):
    """A watcher on the virtual clock whose read of the database takes ``seconds`` of it; while ``held``,
    each read goes on until the test lets one end (``permits.release()``)."""

    def __init__(self, clock: _Clock, seconds: float):
        super().__init__("sqlite:///unused.db")
        self.clock, self.seconds = clock, seconds
        self.held = False
        self.permits = threading.Semaphore(0)
        self._looked = _Looked()

    def read(self) -> dict:
        if self.held:
            self.permits.acquire()
        self.clock.now += self.seconds
        return {"run": None, "reads": self.reads + 1}


@pytest.fixture
def clock(monkeypatch) -> _Clock:
    c = _Clock()
    monkeypatch.setattr(dashboard, "time", c)
    return c


def _idle(w: _Slow) -> int:
    """Start ``w`` with nobody looking, and wait until it has stopped reading; its reads by then."""
    w.start()
    wait_for(lambda: w._looked.waiting, timeout=60, interval=0.01, what="the watcher stops reading")
    return w.reads


def test_reads_take_at_most_their_share_of_the_time(clock):
    """Looked at all the time, a watcher waits POLL_SECONDS between fast reads; a read of 0.2 s at READ_SHARE
    0.05 is followed by a pause of 3.8 s, so that it takes 5 % of the time (the first read, mostly the engine's
    start, is not counted)."""
    for seconds, after in ((0.0, dashboard.POLL_SECONDS), (0.01, dashboard.POLL_SECONDS - 0.01), (0.2, 3.8)):
        clock.pauses, clock.stop_after = [], 5
        w = _Slow(clock, seconds)
        clock.on_sleep = w.looked_at
        with pytest.raises(_Stop):
            w.run()
        assert clock.pauses[0] == dashboard.POLL_SECONDS and clock.pauses[1:] == pytest.approx([after] * 4)
        assert w.reads == 5
        if seconds > dashboard.POLL_SECONDS * dashboard.READ_SHARE:
            assert seconds / (seconds + clock.pauses[-1]) == pytest.approx(dashboard.READ_SHARE)


def test_nobody_looking_nothing_is_read_and_a_look_reads_at_once(clock):
    """Nobody looking, a watcher reads every POLL_SECONDS for the first IDLE_SECONDS (counted as looked at),
    then stops; a look gives at once what was read last, and reading starts again."""
    w = _Slow(clock, 0.0)
    idle = _idle(w)
    assert idle == 1 + round(dashboard.IDLE_SECONDS / dashboard.POLL_SECONDS)
    assert clock.now - 1000.0 > dashboard.IDLE_SECONDS and w.reads == idle  # it waits, and reads nothing
    w.held = True  # the next read goes on until let through
    assert w.looked_at()["reads"] == idle  # what was read last, at once
    w.permits.release()
    wait_for(lambda: w.reads > idle, timeout=60, interval=0.01, what="a read after the look")
    assert w.looked_at()["reads"] == idle + 1


def _ask(w: Watcher, timeout: float | None = None, meanwhile=lambda: None) -> tuple[bool, dict]:
    """Ask ``w`` for the JSON's snapshot: whether it was given at once (there after one turn of the event
    loop, with no wait for a read), and the snapshot; ``meanwhile`` runs after that turn."""

    async def ask():
        task = asyncio.ensure_future(w.fresh(timeout))
        await asyncio.sleep(0)
        at_once = task.done()
        meanwhile()
        return at_once, await task

    return asyncio.run(ask())


def test_the_json_asked_for_after_nobody_looked_is_read_anew(clock):
    """Reading had stopped: the JSON's snapshot comes from a read made after it was asked for, not the one
    made when somebody last looked (a script polling every few minutes would get data as old as its
    interval); asked for again while reading goes on, it is given at once."""
    w = _Slow(clock, 0.2)
    idle = _idle(w)
    w.held = True
    at_once, snap = _ask(w, meanwhile=w.permits.release)  # the read the question starts may end, not the next
    assert not at_once and snap["reads"] == idle + 1  # it waited for that read
    at_once, snap = _ask(w)
    assert at_once and snap["reads"] == idle + 1 and w.reads == idle + 1


def test_the_json_waits_for_a_new_read_no_longer_than_its_timeout(clock, monkeypatch):
    """A read slower than the wait allowed: the snapshot there is, after the wait, and the read goes on."""
    monkeypatch.setattr(dashboard, "POLL_SECONDS", 0.1)
    monkeypatch.setattr(dashboard, "IDLE_SECONDS", 0.3)
    w = _Slow(clock, 0.8)
    assert _idle(w) == 1  # one read, then nobody looks
    w.held = True  # the read the question starts goes on until let through

    def the_wait_allowed_passes():
        clock.now += 0.25

    at_once, snap = _ask(w, timeout=0.2, meanwhile=the_wait_allowed_passes)
    assert not at_once and snap["reads"] == 1 and w.reads == 1  # given after the wait, before the read ended
    w.permits.release()
    wait_for(lambda: w.reads > 1, timeout=60, interval=0.01, what="the read ends")
    assert w.looked_at()["reads"] == 2


def test_the_json_without_a_database_says_so(monkeypatch):
    monkeypatch.setattr(dashboard, "_CURRENT", [])
    assert asyncio.run(dashboard.current_fresh()) == {"run": None, "error": "no database: set PACKINGS_DB"}


def test_the_header_gives_the_papers_count_from_the_fewest_contacts_a_run_keeps(engine):
    """A run restricted by --min-contacts is shown beside the paper's count of clusters with that many contacts
    or more; an n the paper does not count has no such count."""
    from packings.service.db import sessions
    from packings.workers.params import Params

    fill_database(engine, 9, Params(min_contacts=21, max_break=3))
    with sessions(engine)() as s:
        d = dashboard.read_run(s)
    assert (d["n"], d["clusters"], d["paper"], d["min_contacts"]) == (9, 52, 52, 21)
    assert "<td>52 (the paper has 52 with at least 21 contacts)</td>" in dashboard._html(d)
    assert "the paper" not in dashboard._html({**d, "n": 20, "paper": None})


def test_the_header_says_why_a_run_has_fewer_clusters_than_the_paper():
    """n = 11's paths alone reach 1,658 of the paper's 1,659: during them the page says a glued pass follows;
    once passes are recorded, how many; with every cluster found, only the paper's count."""
    d = {
        "run": 1,
        "n": 11,
        "status": "running",
        "clusters": 1500,
        "paper": 1659,
        "min_contacts": None,
        "frontier": {"pending": 5, "leased": 2, "done": 1493, "failed": 0},
        "retries": 0,
        "isolated_failures": 0,
        "glued_passes": 0,
        "at": "now",
    }
    assert "(the paper has 1,659; the paths alone miss some: a glued pass follows them (unless --no-glued)" in (
        dashboard._html(d)
    )
    stopped = dashboard._html({**d, "status": "complete", "clusters": 1658})
    assert "the glued pass after them (`packings enumerate 11`) adds those)" in stopped
    assert "(the paper has 1,659; 1 glued pass made, its finds being expanded)" in dashboard._html(
        {**d, "glued_passes": 1}
    )
    assert "<td>1,659 (the paper has 1,659)</td>" in dashboard._html({**d, "status": "complete", "clusters": 1659})


def test_the_rate_is_drawn_from_zero(monkeypatch):
    """A steady 42 expansions per second, swinging by 1 %, is not drawn as a collapse: the axis starts at 0."""
    from bokeh.document import Document
    from bokeh.plotting import figure

    monkeypatch.setattr(dashboard, "_CURRENT", [])  # no database: the page's frame alone
    doc = Document()
    dashboard.packings_doc(None, {}, doc)
    [rate] = [f for f in doc.select({"type": figure}) if f.title.text == "expansions per second"]
    assert rate.y_range.start == 0
