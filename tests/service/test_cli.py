"""The packings command line, run as a user runs it."""

import json
import subprocess
import sys

import pytest


def run(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "packings.service.cli", *args], capture_output=True, text=True, timeout=600, cwd=cwd
    )


def test_enumerate_prints_the_table(sqlite_url):
    r = run("enumerate", "7", "--quiet", "--db", sqlite_url)
    assert r.returncode == 0, r.stderr
    assert "n = 7: 5 rigid clusters" in r.stdout
    assert "\nas the paper at every number of contacts: 5 (Holmes-Cerfon" in r.stdout
    assert "diagnostics:" in r.stdout


def test_enumerate_json(paper_counts, sqlite_url):
    r = run("enumerate", "8", "--json", "--quiet", "--db", sqlite_url)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["n"] == 8 and out["total"] == paper_counts["totals"]["8"]
    assert out["by_contacts"] == paper_counts["clusters_by_contacts"]["8"]
    assert out["diagnostics"]["expansions"] == 13
    assert out["paper"]["same"] is True and out["paper"]["by_contacts"] == out["by_contacts"]


def test_bad_n_is_one_line_and_nonzero(tmp_path):
    for n in ("3", "500"):
        r = run("enumerate", n, cwd=tmp_path)
        assert r.returncode != 0
        assert r.stdout == ""
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("packings: error:"), r.stderr
        assert "Traceback" not in r.stderr
        assert list(tmp_path.iterdir()) == []  # nothing written


def test_help():
    r = run("enumerate", "--help")
    assert r.returncode == 0 and "--max-break" in r.stdout


# A command whose main thread is inside a finalizer (as a Dask Future's or a connection's __del__ may be) when the
# signal's handler runs: Python prints what the handler raised there ("Exception ignored in ...") and goes on
SIGNAL_IN_A_FINALIZER = r"""
import os, signal, sys, time

import click

from packings.service import cli


def signal_and_spin():
    os.kill(os.getpid(), getattr(signal, sys.argv[1]))
    t = time.monotonic()
    while time.monotonic() - t < 0.5:  # the handler runs here, between two bytecodes
        pass


class Finalized:
    def __del__(self):
        if sys.argv[2] == "hook":  # another error, whose report (the unraisable hook) the signal lands in
            raise ValueError("not the signal's")
        signal_and_spin()


if sys.argv[2] == "hook":
    sys.unraisablehook = lambda unraisable: signal_and_spin()


@cli.cli.command("spin")
def spin():
    Finalized()  # dropped at once: its finalizer runs
    time.sleep(5)
    click.echo("ran to its end")


cli.main(["spin"])
"""


@pytest.mark.parametrize("where", ["finalizer", "hook"])
def test_a_signal_that_lands_in_a_finalizer_still_stops_the_command(where):
    """SIGTERM (and Ctrl-C's SIGINT) whose handler runs inside a finalizer, or inside the report of another
    finalizer's error, where Python swallows what it raises, still stops the command at once: its one line
    and exit status, no traceback, not a command that goes on to its end with exit status 0."""
    for name, status, line in (
        ("SIGTERM", 143, "packings: terminated (SIGTERM); run the same command to resume"),
        ("SIGINT", 130, "packings: interrupted; run the same command to resume"),
    ):
        r = subprocess.run(
            [sys.executable, "-c", SIGNAL_IN_A_FINALIZER, name, where], capture_output=True, text=True, timeout=60
        )
        assert r.returncode == status, (name, r.stdout, r.stderr)
        assert "ran to its end" not in r.stdout
        assert r.stderr.strip().splitlines() == [line], (name, r.stderr)


# main called off the main thread (from a notebook's worker thread, say), by a command that sets the unraisable
# hook as another thread might while it runs
HOOK_OFF_THE_MAIN_THREAD = r"""
import sys, threading

from packings.service import cli


def mine(unraisable):
    pass


seen = []


@cli.cli.command("hook")
def hook():
    seen.append(sys.unraisablehook)
    sys.unraisablehook = mine


before = sys.unraisablehook
thread = threading.Thread(target=cli.main, args=(["hook"],))
thread.start()
thread.join()
print(seen == [before], sys.unraisablehook is mine)
"""


def test_main_off_the_main_thread_leaves_the_unraisable_hook_alone():
    """Only in the main thread does main set its own unraisable hook (and put the previous one back when it
    returns): elsewhere it neither sets one nor undoes one that was set while it ran."""
    r = subprocess.run([sys.executable, "-c", HOOK_OFF_THE_MAIN_THREAD], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["True", "True"]
