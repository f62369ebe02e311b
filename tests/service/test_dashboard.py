"""The packings page of the Dask dashboard, fetched over HTTP during real runs."""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import sys
import time
import urllib.request

import pytest
from sqlalchemy import text

from benchmarks.screenshot import render
from packings.db import make_engine
from tests.service.test_enumerate import _free_port, done_count, packings, wait_for


CHROMIUM = shutil.which("chromium")


def fetch(url: str, timeout: float = 10.0) -> tuple[int, str]:
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return r.status, r.read().decode()


def _database_now(url: str) -> dict:
    engine = make_engine(url)
    with engine.connect() as c:
        done = c.execute(text("SELECT count(*) FROM expansions WHERE status = 'done'")).scalar()
        clusters = c.execute(text("SELECT count(*) FROM expansions")).scalar()
    engine.dispose()
    return {"done": done, "clusters": clusters}


def test_the_page_shows_the_run_as_the_database_has_it(db_url):
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "packings.cli", "enumerate", "10", "--db", db_url, "--workers", "2",
                             "--dashboard-address", f"127.0.0.1:{port}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
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
        _, dask_status = fetch(f"http://127.0.0.1:{port}/status")
        out, err = proc.communicate(timeout=900)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    snap = json.loads(body)
    assert status == 200 and (snap["run"], snap["n"], snap["status"]) == (1, 10, "running")
    # read within a second or two before the fetch: between what the database had before and after it
    assert snap["frontier"]["done"] <= after["done"] and snap["clusters"] <= after["clusters"]
    assert snap["frontier"]["done"] >= 20 and snap["clusters"] >= 20
    assert sum(snap["frontier"].values()) == snap["clusters"] == sum(snap["by_contacts"].values())
    assert snap["rate"] > 0 and snap["eta_seconds"] is not None and snap["failed"] == []
    assert sum(w["done"] for w in snap["workers"]) == snap["frontier"]["done"] and len(snap["workers"]) <= 2
    assert before["done"] >= 20
    assert page_status == 200 and "Dask Diagnostic UI" in page and "bokeh" in page  # the Bokeh document's page
    assert 'href="packings"' in dask_status  # in the dashboard's navigation bar
    assert f"dashboard http://127.0.0.1:{port}/packings" in err


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (Debian: apt-get install chromium)")
def test_the_page_draws_in_a_browser(sqlite_url):
    """Headless Chromium draws the page during a run: the run's numbers, and no script error."""
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "packings.cli", "enumerate", "10", "--db", sqlite_url,
                             "--workers", "2", "--quiet", "--dashboard-address", f"127.0.0.1:{port}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: done_count(sqlite_url) >= 5, proc)
        drawn = render(f"http://127.0.0.1:{port}/packings", wait=3.0)
        proc.communicate(timeout=900)
    finally:
        proc.kill()
    assert drawn["errors"] == [] and "run 1 (n = 10), running" in drawn["text"], drawn["text"][-600:]
    assert "clusters found" in drawn["text"] and "expansions done" in drawn["text"]
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
