"""The Python API (packings.connect, packings.enumerate) on SQLite and PostgreSQL: the same
selection language, facts and errors as the command line, whose JSON output it must equal."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from sqlalchemy import text

import packings
from packings.service.errors import NotFound, PackingsError, UsageError
from tests.helpers import fill_database


def cli_json(url: str, *args: str):
    r = subprocess.run(
        [sys.executable, "-m", "packings.service.cli", *args, "--db", url, "--json"],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    return json.loads(r.stdout)


@pytest.fixture
def cat(filled):
    url = filled.url.render_as_string(hide_password=False)
    with packings.connect(url) as c:
        yield c


def test_select_count_and_equalities_agree(cat):
    assert cat.count() == 5 + 13
    assert cat.count("n=8") == cat.count(n=8) == 13 == len(list(cat.select(n=8)))
    rigid_8 = [r.id for r in cat.select("n=8,contacts=18")]
    assert rigid_8 == [r.id for r in cat.select(n=8, contacts=18)] == [r.id for r in cat.select("n=8", contacts=18)]
    assert len(rigid_8) == cat.count("n=8,contacts=18") > 0
    assert [r.id for r in cat.select(n=7, singular=False)] == [r.id for r in cat.select("n=7,!singular")]


def test_select_sorts_and_limits(cat):
    gaps = [r.min_gap for r in cat.select(n=8, sort="-min_gap")]
    assert gaps == sorted(gaps, reverse=True) and len(gaps) == 13
    assert [r.min_gap for r in cat.select(n=8, sort="-min_gap", limit=3)] == gaps[:3]
    assert list(cat.select(limit=0)) == []


def test_bad_selections_fail_before_anything_is_read(cat):
    for bad in ("n==7", "colour=red", "contacts=many"):
        with pytest.raises(UsageError):
            cat.select(bad)  # raised by the call, not when the rows are read
    with pytest.raises(UsageError):
        cat.count(colour="red")
    with pytest.raises(UsageError):
        cat.select(sort="colour")


def test_a_row_is_the_stored_cluster_bit_for_bit(cat, filled):
    row = cat.get(3)
    with filled.connect() as conn:
        blob, pairs, n, m = conn.execute(
            text("SELECT coords, contact_pairs, n, contacts FROM clusters WHERE id = 3")
        ).one()
    assert row.coords.dtype == np.float64 and row.coords.shape == (n, 3)
    assert row.coords.astype("<f8").tobytes() == bytes(blob)
    assert row.contacts.shape == (m, 2) and row.contacts.dtype.kind == "i"
    assert row.contacts.astype(np.uint8).tobytes() == bytes(pairs) and len(row.contacts) == row.facts["contacts"]
    assert (row.id, row.n) == (3, n) and row.lattice == row.facts["lattice"]
    with pytest.raises(AttributeError, match="no fact 'colour'"):
        row.colour


def test_get_of_a_missing_id_is_a_key_error(cat):
    with pytest.raises(NotFound, match="no cluster with id 999") as e:
        cat.get(999)
    assert isinstance(e.value, KeyError) and isinstance(e.value, PackingsError)


def test_what_the_api_returns_is_what_the_command_line_prints(cat):
    url = cat.url
    assert cat.stats() == cli_json(url, "stats")
    assert cat.stats(8) == cli_json(url, "stats", "--n", "8")
    assert cat.runs() == cli_json(url, "status")
    assert [r.record() for r in cat.select("n=7")] == cli_json(url, "select", "n=7")
    show = cli_json(url, "show", "4")
    assert {**cat.get(4).record(), **cat.links(4), "exact": dataclasses.asdict(cat.get(4).exact())} == show


def test_a_rows_exact_root_is_proved_where_it_has_no_flex(cat):
    """Row.exact(): Kantorovich's theorem on the stored coordinates (packings.workers.exact); None where the
    cluster has a flex.  Every cluster of the filled catalogue is proved, its gap bound its min_gap."""
    rows = cat.select("")
    assert rows
    for row in rows:
        e = row.exact()
        if row.flexes:
            assert e is None
        else:
            assert e.proved and 0 < e.radius < 1e-12 and abs(e.gap - row.min_gap) < 1e-12


def test_transitions_are_the_paths_leaving_and_reaching_a_cluster(cat):
    for row in cat.select(n=8):
        links = cat.links(row.id)
        leaving = cat.transitions(row.id)
        assert all(t["source"] == row.id for t in leaving)
        assert sum(t["direction"] != 0 for t in leaving) == links["paths_leaving"]
        reaching = [t for t in cat.transitions(row.id, reaching=True) if t["direction"] != 0]
        assert all(t["target"] == row.id for t in reaching) and len(reaching) == links["paths_reaching"]
        assert all(len(p) == 2 for t in leaving for p in t["broken"])
    with pytest.raises(NotFound):
        cat.transitions(999)


def test_to_atoms_carries_the_geometry_and_the_facts(cat):
    pytest.importorskip("ase")
    row = cat.get(2)
    atoms = row.to_atoms()
    assert np.array_equal(atoms.get_positions(), row.coords)
    assert set(atoms.get_chemical_symbols()) == {"X"}
    assert atoms.info["cluster_id"] == 2 and atoms.info["contacts"] == len(row.contacts)
    assert "id" not in atoms.info and "stresses" not in atoms.info, "names ASE's database reserves"
    assert np.array_equal(atoms.info["contact_pairs"], row.contacts)


def test_to_atoms_without_ase_says_what_to_install(cat, monkeypatch):
    monkeypatch.setitem(sys.modules, "ase", None)  # import ase raises ImportError
    with pytest.raises(ImportError, match="pip install ase"):
        cat.get(1).to_atoms()


def test_connect_refuses_a_missing_database_and_writes_nothing(tmp_path, monkeypatch):
    path = tmp_path / "none.db"
    with pytest.raises(PackingsError, match="no database"):
        packings.connect(str(path))
    assert not path.exists()
    monkeypatch.setenv("PACKINGS_DB", f"sqlite:///{path}")
    with packings.connect(create=True) as c:  # the default URL is the command line's
        assert c.count() == 0 and c.runs() == [] and c.url == f"sqlite:///{path}"
    assert path.is_file()


def test_enumerate_runs_and_resumes(db_url):
    with pytest.raises(UsageError, match="at least 4"):
        packings.enumerate(3, db_url)
    with pytest.raises(UsageError, match="not both"):
        packings.enumerate(6, db_url, workers=1, scheduler="tcp://127.0.0.1:1")
    result = packings.enumerate(7, db_url, workers=1, progress=False)
    assert (result.status, result.total, result.resumed) == ("complete", 5, False)
    again = packings.enumerate(7, db_url, workers=1, progress=False)
    assert (again.status, again.total, again.resumed, again.run_id) == ("complete", 5, True, result.run_id)
    with packings.connect(db_url) as c:
        assert c.count(n=7) == 5 and c.runs()[0]["status"] == "complete"


def test_a_script_that_enumerates_outside_the_main_guard_is_told_why_in_one_line(tmp_path):
    """The workers of a local cluster import the script that starts them: one that calls enumerate at its
    top level calls it again in each of them.  The script is told why once, in the one line of its error,
    where multiprocessing printed a traceback of its own in each worker at each try to start the cluster
    (and then each worker said why, once a try); the file the workers mark it with is gone after.  The
    same database then serves a script that calls it under the guard."""
    from packings.service.dask_cluster import UNGUARDED

    url = f"sqlite:///{tmp_path / 'unguarded.db'}"
    script = tmp_path / "unguarded.py"
    script.write_text(f"import packings\npackings.enumerate(7, {url!r}, workers=2, progress=False)\n")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {**os.environ, "TMPDIR": str(tmp)}
    env.pop("PACKINGS_UNGUARDED_MARK", None)
    r = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=600, cwd=tmp_path, env=env
    )
    assert r.returncode != 0
    last = r.stderr.splitlines()[-1]
    assert "the local Dask cluster failed to start" in last and last.endswith(UNGUARDED), r.stderr
    assert r.stderr.count("packings.enumerate at its top level") == 1, r.stderr
    assert "trying again" not in r.stderr and "bootstrapping phase" not in r.stderr
    assert r.stderr.count("Traceback") <= 1  # the script's own: the PackingsError it did not catch
    assert list(tmp.glob("packings-unguarded-*")) == []
    guarded = script.with_name("guarded.py")
    guarded.write_text(
        f"import packings\nif __name__ == '__main__':\n"
        f"    print(packings.enumerate(7, {url!r}, workers=1, progress=False).total)\n"
    )
    r = subprocess.run(
        [sys.executable, str(guarded)], capture_output=True, text=True, timeout=600, cwd=tmp_path, env=env
    )
    assert (r.returncode, r.stdout.split()[-1:], UNGUARDED in r.stderr) == (0, ["5"], False), r.stderr
    assert list(tmp.glob("packings-unguarded-*")) == []


def test_a_worker_that_ran_its_parents_script_marks_the_file_its_parent_named(tmp_path, monkeypatch, capsys):
    """A new process importing its parent's script ends at once: silently where the parent named a file
    for it to create (its parent then says why), in one line where it named none."""
    import multiprocessing

    from packings.service import dask_cluster

    monkeypatch.setattr(multiprocessing.current_process(), "_inheriting", True, raising=False)
    mark = tmp_path / "mark"
    monkeypatch.setenv(dask_cluster.UNGUARDED_MARK_ENV, str(mark))
    with pytest.raises(SystemExit) as e:
        dask_cluster.start_fork_server()
    assert (e.value.code, mark.exists(), capsys.readouterr().err) == (1, True, "")
    assert dask_cluster._ran_unguarded() and not mark.exists() and not dask_cluster._ran_unguarded()
    monkeypatch.delenv(dask_cluster.UNGUARDED_MARK_ENV)
    with pytest.raises(SystemExit) as e:
        dask_cluster.start_fork_server()
    err = capsys.readouterr().err
    assert (e.value.code, err.count("\n"), err.strip().endswith(dask_cluster.UNGUARDED)) == (1, 1, True), err


def test_the_readme_example_runs(filled, tmp_path, monkeypatch):
    """The README's Python block, as written, on a database holding n = 7 and 8 (and one of n = 10)."""
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    (block,) = [b.split("\n", 1)[1] for b in readme.split("```")[1:] if b.startswith("python\n")]
    url = filled.url.render_as_string(hide_password=False)
    assert 'packings.connect("sqlite:///packings.db")' in block
    code = block.replace('"sqlite:///packings.db"', repr(url))
    monkeypatch.chdir(tmp_path)
    pytest.importorskip("ase")
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["atoms"].info["cluster_id"] == 1


def test_a_run_held_by_a_live_coordinator_is_refused_before_anything_starts(engine, monkeypatch):
    import os
    import socket

    import packings.service.run
    from packings.service import store
    from packings.service.db import sessions
    from packings.workers.params import Params

    url = engine.url.render_as_string(hide_password=False)
    store.start_run(sessions(engine), 8, Params(), f"{socket.gethostname()}:{os.getpid()}:holder")  # alive: us

    def no_dask(*args, **kw):
        raise AssertionError("a Dask cluster was started")

    monkeypatch.setattr(packings.service.run, "dask_client", no_dask)
    with pytest.raises(PackingsError, match="being driven by coordinator"):
        packings.enumerate(8, url, workers=1, progress=False)
    r = subprocess.run(
        [sys.executable, "-m", "packings.service.cli", "enumerate", "8", "--db", url],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [r.stderr.strip()] and "being driven by coordinator" in r.stderr


def test_status_says_interrupted_and_stats_says_partial(engine):
    import os
    import socket

    from packings.service import store
    from packings.service.db import sessions
    from packings.workers.params import Params

    url = engine.url.render_as_string(hide_password=False)
    S = sessions(engine)
    dead = f"{socket.gethostname()}:{2**22 + 12345}:gone"  # above Linux's largest pid: no such process
    store.start_run(S, 7, Params(), dead)
    with packings.connect(url) as cat:
        assert cat.runs()[0]["status"] == "interrupted"
        assert cat.stats(7)[0]["complete"] is False
        assert cat.fit() is None and cat.stats(7)[0]["fit"] is None  # a partial count is never fitted
    text = subprocess.run(
        [sys.executable, "-m", "packings.service.cli", "stats", "--db", url],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    ).stdout
    assert "n = 7: 1 rigid cluster so far (partial" in text
    store.start_run(S, 7, Params(), f"{socket.gethostname()}:{os.getpid()}:live")  # taken over by a live one
    with packings.connect(url) as cat:
        assert cat.runs()[0]["status"] == "running"
    fill_database(engine, 6)  # a whole run of n = 6, to the end
    with packings.connect(url) as cat:
        assert [r["status"] for r in cat.runs()] == ["running", "complete"]
        assert [(d["n"], d["complete"]) for d in cat.stats()] == [(6, True), (7, False)]
        fit = cat.fit()
        assert fit["ns"] == [6] and cat.stats(7)[0]["fit"]["predicted"] == pytest.approx(2 * fit["b"])


def test_a_complete_run_capped_by_max_break_is_partial(engine):
    """A run of n = 8 complete with --max-break 1 and no --min-contacts is not the method's full count of
    n = 8 (the paper caps nothing up to n = 14): stats says partial and the fit leaves it out."""
    from packings.workers.params import Params

    fill_database(engine, 7)
    fill_database(engine, 8, Params(max_break=1))
    url = engine.url.render_as_string(hide_password=False)
    with packings.connect(url) as cat:
        assert [r["status"] for r in cat.runs()] == ["complete", "complete"]
        assert [(d["n"], d["complete"]) for d in cat.stats()] == [(7, True), (8, False)]
        assert cat.fit()["ns"] == [7] and cat.stats(8)[0]["fit"]["predicted"] == pytest.approx(6 * cat.fit()["b"])
    text = subprocess.run(
        [sys.executable, "-m", "packings.service.cli", "stats", "--db", url],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    ).stdout
    assert "(partial: no full run of n = 8 is complete)" in text


def test_runs_restricted_by_min_contacts_are_shown_as_such_and_left_out_of_the_fit(engine, tmp_path):
    """n = 7 and 8 in full, n = 9 only from a run restricted by --min-contacts: stats, the fit and the
    counts figure keep n = 9 apart."""
    from packings.service.plots import plot_counts
    from packings.service.stats import fit_all
    from packings.workers.params import Params

    fill_database(engine, 7)
    fill_database(engine, 8)
    fill_database(engine, 9, Params(min_contacts=21, max_break=3))
    url = engine.url.render_as_string(hide_password=False)
    with packings.connect(url) as cat:
        stats = {d["n"]: d for d in cat.stats()}
        fit = cat.fit()
    assert [stats[n]["min_contacts"] for n in (7, 8, 9)] == [None, None, 21]
    assert stats[9]["total"] == 52 and not stats[9]["complete"]
    assert fit["ns"] == [7, 8] and fit == fit_all({7: {15: 5}, 8: {18: 13}})
    assert stats[8]["fit"]["b"] == stats[9]["fit"]["b"] == fit["b"]
    text = subprocess.run(
        [sys.executable, "-m", "packings.service.cli", "stats", "--db", url],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    ).stdout
    assert "n = 9: 52 rigid clusters with at least 21 contacts (runs restricted by --min-contacts" in text
    assert "as the paper at every number of contacts, with at least 21 contacts: 52 (" in text
    assert stats[9]["paper"]["by_contacts"] == {"21": 52} and stats[9]["paper"]["same"] is True
    assert "n = 8: 13 rigid clusters (" in text
    fig = plot_counts({7: 5, 8: 13, 9: 52}, restricted={9: 21})
    [ax] = fig.axes
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "rigid clusters",
        "clusters with ≥ M contacts only (--min-contacts M)",
        f"fit {fit['b']:.2f}·(n − 5)!  (n = 7–8)",
    ]
    assert "52\n(≥ 21)" in [t.get_text() for t in ax.texts]
    fill_database(engine, 9)  # a full run of n = 9: no longer restricted
    with packings.connect(url) as cat:
        assert cat.stats(9)[0]["min_contacts"] is None and cat.fit()["ns"] == [7, 8, 9]


def test_a_restricted_run_with_no_seed_that_has_enough_contacts_is_refused_in_one_line(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "packings.service.cli",
            "enumerate",
            "10",
            "--min-contacts",
            "26",
            "--db",
            f"sqlite:///{tmp_path / 'x.db'}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode != 0 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        "packings: error: no cluster of 10 spheres with at least 26 contacts to start from: no rigid close-packed "
        "fragment has that many"
    ], r.stderr
    assert not (tmp_path / "x.db").exists()  # refused before anything is created
