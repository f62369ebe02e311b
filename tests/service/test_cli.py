"""The packings command line, run as a user runs it."""

import json
import subprocess
import sys


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "packings.cli", *args], capture_output=True, text=True, timeout=600,
                          cwd=cwd)


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
