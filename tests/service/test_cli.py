"""The packings command line, run as a user runs it."""

import json
import signal
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
            [sys.executable, "-c", SIGNAL_IN_A_FINALIZER, name, where],
            capture_output=True,
            text=True,
            timeout=60,
            # Ctrl-C's default, as at a terminal: a suite started in the background by a shell without job
            # control hands its processes SIGINT ignored, which Python then leaves ignored
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
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


def _one_line(r, status: int, *words) -> str:
    """``r`` ended with exit ``status`` and one line on standard error, holding ``words``; the line."""
    assert r.returncode == status, (r.args, r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("packings: error: "), r.stderr
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]


def test_one_name_per_quantity_of_paths(sqlite_url):
    """enumerate's paths_followed counts the paths integrated; stats counts every path stored (followed, by
    symmetry or retraced), as the paper counts paths, with the number followed beside it."""
    r = run("enumerate", "8", "--json", "--quiet", "--workers", "1", "--no-glued", "--db", sqlite_url)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)["diagnostics"]
    every = d["paths_followed"] + d["paths_by_symmetry"] + d["paths_retraced"]
    assert d["paths_by_symmetry"] > 0 and d["paths_retraced"] > 0
    (stats,) = json.loads(run("stats", "--json", "--db", sqlite_url).stdout)
    assert stats["paths"] == every
    assert stats["paths_followed"] == d["paths_followed"] < every
    text = run("stats", "--db", sqlite_url).stdout
    assert f"as the paper counts them): {every}, of which {d['paths_followed']} followed (the others" in text


def test_exit_status_nothing_there_is_1_a_malformed_request_2(sqlite_url, tmp_path):
    """One rule: a well-formed request for what the database does not hold (an id, an n) ends with one line
    and exit status 1; malformed input (not a number, a value a key cannot take, a file name whose format
    cannot be told) with one line and exit status 2."""
    assert run("enumerate", "7", "--quiet", "--workers", "1", "--db", sqlite_url).returncode == 0
    _one_line(run("show", "999999", "--db", sqlite_url), 1, "no cluster with id 999999")
    for command in (["stats"], ["audit"], ["plot", "counts", "-o", str(tmp_path / "c.png")]):
        _one_line(run(*command, "--n", "99", "--db", sqlite_url), 1, "no clusters with n = 99")
    _one_line(run("show", "abc", "--db", sqlite_url), 2, "'abc' is not a valid integer")
    _one_line(run("select", "lattice=bcc", "--db", sqlite_url), 2, "expected one of fcc, hcp")
    _one_line(run("export", "-o", str(tmp_path / "x.pdb"), "--db", sqlite_url), 2, "cannot tell the format of")
    assert not (tmp_path / "x.pdb").exists()
    # a format given outright goes into any file name; a known suffix chooses its own
    r = run("export", "-o", str(tmp_path / "x.pdb"), "--format", "xyz", "--db", sqlite_url)
    assert r.returncode == 0 and r.stdout.strip().endswith("(xyz) to " + str(tmp_path / "x.pdb")), r.stderr
    r = run("export", "n=7,contacts=15,id=1", "-o", str(tmp_path / "one.json"), "--db", sqlite_url)
    assert r.returncode == 0 and r.stdout.startswith("wrote 1 cluster (json) to "), r.stdout  # not "1 clusters"
    r = run("select", "id=1", "--db", sqlite_url)
    assert r.stdout.splitlines()[-1] == "1 cluster"
    assert run("audit", "--n", "7", "--db", sqlite_url).stdout.startswith("audit of 1 value of n (n = 7: ")


def _read_only_directory(directory, files=()):
    """Make ``directory`` one this process cannot write in, holding copies of ``files``: a read-only tmpfs
    mounted there for root (whom permissions do not stop; skipped where it cannot mount), else mode 555."""
    import os
    import shutil

    directory.mkdir()
    if os.geteuid() != 0:
        for f in files:
            shutil.copy(f, directory)
        directory.chmod(0o555)
        return lambda: directory.chmod(0o755)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(directory)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()[:120]}")
    for f in files:
        shutil.copy(f, directory)
    subprocess.run(["mount", "-o", "remount,ro", str(directory)], check=True)
    return lambda: subprocess.run(["umount", "-l", str(directory)], capture_output=True)


def test_a_directory_that_cannot_be_written_is_named(tmp_path):
    """SQLite said only "unable to open database file" of a database in a directory it cannot write in (its
    journal goes beside the file): the directory is named, to open one there or to create one."""
    db = tmp_path / "packings.db"
    assert run("db", "upgrade", "--db", f"sqlite:///{db}").returncode == 0
    ro = tmp_path / "ro"
    undo = _read_only_directory(ro, [db])
    try:
        line = _one_line(run("stats", "--db", f"sqlite:///{ro / 'packings.db'}"), 1)
        assert line == (
            f"packings: error: cannot open {ro / 'packings.db'}: directory {ro} is not writable (SQLite keeps its "
            "journal beside the database file): make it writable, or move the database"
        )
        r = run("enumerate", "7", "--quiet", "--workers", "1", "--db", f"sqlite:///{ro / 'new.db'}")
        _one_line(r, 1, f"cannot create {ro / 'new.db'}: directory {ro} is not writable")
    finally:
        undo()


def test_the_python_apis_missing_database_error_names_no_option(tmp_path):
    """The same words from connect() and from the command line: no option of the command line's."""
    import packings

    with pytest.raises(packings.PackingsError) as e:
        packings.connect(f"sqlite:///{tmp_path / 'none.db'}")
    assert str(e.value).startswith(f"no database at {tmp_path / 'none.db'}: run `packings enumerate N` to make one")
    assert "--db" not in str(e.value)
    line = _one_line(run("select", "--db", f"sqlite:///{tmp_path / 'none.db'}"), 1)
    assert line == f"packings: error: {e.value}"


def test_a_passs_bar_starts_after_the_cluster_is_announced(sqlite_url):
    """catalyse's bar, as enumerate's, is drawn from the pass's first progress on: the cluster's line is not
    written onto it."""
    assert run("enumerate", "6", "--quiet", "--workers", "1", "--db", sqlite_url).returncode == 0
    r = run("catalyse", "6", "--glued", "--workers", "1", "--db", sqlite_url)
    assert r.returncode == 0, r.stderr
    assert "dask: local cluster" in r.stderr and "clusters of 6" in r.stderr
    before, bar = r.stderr.split("clusters of 6", 1)
    assert "dask: local cluster" in before and "dask:" not in bar, r.stderr
