"""The packings page of the Dask dashboard, fetched over HTTP during real runs."""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
import subprocess
import sys
import time

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
    try:
        wait_for(lambda: done_count(db_url) >= 20, proc)
        time.sleep(1.5)  # a read of the database by the page's thread since
        # the rate needs two of the page's reads with expansions done between them: at the start of a
        # fast run a second or two can pass without a write-back, so read the page until it has one
        for _ in range(20):
            before = _database_now(db_url)
            status, body = fetch(f"http://127.0.0.1:{port}/packings.json")
            after = _database_now(db_url)
            if json.loads(body).get("rate", 0) > 0 or proc.poll() is not None:
                break
            time.sleep(0.5)
        page_status, page = fetch(f"http://127.0.0.1:{port}/packings")
        # Dask's own page renders its plots on the first request: seconds where the cores are shared
        _, dask_status = fetch(f"http://127.0.0.1:{port}/status", timeout=60.0)
        out, err = proc.communicate(timeout=900)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    snap = json.loads(body)
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
        drawn = render(f"http://127.0.0.1:{port}/packings", wait=3.0)
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


class _Slow(Watcher):
    """A watcher whose read of the database takes ``seconds``."""

    def __init__(self, seconds: float):
        super().__init__("sqlite:///unused.db")
        self.seconds = seconds

    def read(self) -> dict:
        time.sleep(self.seconds)
        return {"run": None, "reads": self.reads + 1}


def _reads_over(w: Watcher, seconds: float, look: bool) -> int:
    """How many reads ``w`` makes in ``seconds`` after it starts, looked at every 0.05 s or not at all."""
    w.start()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if look:
            w.looked_at()
        time.sleep(0.05)
    return w.reads


def test_reads_take_at_most_their_share_of_the_time(monkeypatch):
    """Looked at all the time, a watcher whose reads take 0.2 s reads every 4 s at READ_SHARE 0.05, not
    every POLL_SECONDS: 1 or 2 reads in 3 s (a fast read: every POLL_SECONDS)."""
    monkeypatch.setattr(dashboard, "POLL_SECONDS", 0.1)
    assert 1 <= _reads_over(_Slow(0.2), 3.0, look=True) <= 2
    assert _reads_over(_Slow(0.0), 1.5, look=True) >= 5


def test_nobody_looking_nothing_is_read_and_a_look_reads_at_once(monkeypatch):
    monkeypatch.setattr(dashboard, "POLL_SECONDS", 0.1)
    monkeypatch.setattr(dashboard, "IDLE_SECONDS", 0.3)
    w = _Slow(0.0)
    idle = _reads_over(w, 2.0, look=False)
    assert 1 <= idle <= 6  # the first IDLE_SECONDS count as looked at, then nothing
    time.sleep(0.5)
    assert w.reads == idle
    snap = w.looked_at()
    assert snap["reads"] == idle  # what was read last, at once
    for _ in range(100):
        if w.reads > idle:
            break
        time.sleep(0.02)
    assert w.reads > idle and w.looked_at()["reads"] > idle


def test_the_json_asked_for_after_nobody_looked_is_read_anew(monkeypatch):
    """Reading had stopped: the JSON's snapshot comes from a read made after it was asked for, not the one
    made when somebody last looked (a script polling every few minutes would get data as old as its
    interval); asked for again while reading goes on, it is given at once."""
    monkeypatch.setattr(dashboard, "POLL_SECONDS", 0.1)
    monkeypatch.setattr(dashboard, "IDLE_SECONDS", 0.3)
    w = _Slow(0.2)
    idle = _reads_over(w, 2.0, look=False)
    time.sleep(0.5)
    assert w.reads == idle
    start = time.monotonic()
    assert asyncio.run(w.fresh())["reads"] == idle + 1
    assert time.monotonic() - start >= 0.2  # it waited for that read
    start = time.monotonic()
    assert asyncio.run(w.fresh())["reads"] == idle + 1 and time.monotonic() - start < 0.15


def test_the_json_waits_for_a_new_read_no_longer_than_its_timeout(monkeypatch):
    """A read slower than the wait allowed: the snapshot there is, after the wait, and the read goes on."""
    monkeypatch.setattr(dashboard, "POLL_SECONDS", 0.1)
    monkeypatch.setattr(dashboard, "IDLE_SECONDS", 0.3)
    w = _Slow(0.8)
    _reads_over(w, 1.5, look=False)  # one read, then nobody looks
    assert w.reads == 1
    start = time.monotonic()
    assert asyncio.run(w.fresh(timeout=0.2))["reads"] == 1  # returned before the read (0.8 s) ended
    assert time.monotonic() - start >= 0.2
    for _ in range(100):
        if w.reads > 1:
            break
        time.sleep(0.02)
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
