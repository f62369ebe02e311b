"""The query commands (select, show, export), run as a user runs them, on both backends."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys

import numpy as np
import pytest
from sqlalchemy import select

from packings.service import queries
from packings.service.models import ClusterRow
from tests.helpers import filled_catalog, ok, one_line_error, run_many
from tests.helpers import packings as run

catalog = filled_catalog(7, 8)

TABLE_HEADER = [
    "id",
    "n",
    "contacts",
    "embedding",
    "singular",
    "flexes",
    "stresses",
    "min_gap",
    "lattice",
    "certificate",
]


@pytest.fixture(scope="module")
def stored(catalog):
    """{id: (row, exact coordinates)} of every stored cluster."""
    from packings.service.db import sessions

    with sessions(catalog.engine)() as s:
        rows = s.execute(select(ClusterRow).order_by(ClusterRow.n, ClusterRow.contacts, ClusterRow.id)).scalars().all()
    return {c.id: (c, c.to_core().coords) for c in rows}


def read_xyz(text: str) -> list[tuple[str, list[str], np.ndarray]]:
    """Frames of an XYZ file: (comment, species, coordinates parsed with float())."""
    lines, frames = text.splitlines(), []
    while lines:
        k = int(lines[0])
        body = [line.split() for line in lines[2 : 2 + k]]
        frames.append((lines[1], [b[0] for b in body], np.array([[float(v) for v in b[1:]] for b in body])))
        lines = lines[2 + k :]
    return frames


# --------------------------------------------------------------------------- select


def test_select_table(catalog, stored):
    out = ok("select", "--db", catalog.url).splitlines()
    assert out[0].split() == TABLE_HEADER
    assert [int(line.split()[0]) for line in out[1:-1]] == list(stored)
    assert out[-1] == "18 clusters"
    out = ok("select", "n=8,contacts<18", "--db", catalog.url)
    assert out.strip() == "no clusters match"


def test_select_table_limits_and_columns_as_ase_db(catalog, stored, monkeypatch):
    out = ok("select", "--limit", "5", "--db", catalog.url).splitlines()
    assert [int(line.split()[0]) for line in out[1:-1]] == list(stored)[:5]
    assert out[-1] == "5 of 18 clusters (13 more: --limit 0 shows all)"
    out = ok("select", "--limit", "0", "--db", catalog.url).splitlines()
    assert len(out) == 1 + 18 + 1 and out[-1] == "18 clusters"
    out = ok("select", "n=7", "-c", "id,lattice,found_by", "--db", catalog.url).splitlines()
    assert out[0].split() == ["id", "lattice", "found_by"] and {line.split()[2] for line in out[1:-1]} <= {
        "seed",
        "path",
    }
    out = ok("select", "n=7", "-c", "+margin,+found_by", "--db", catalog.url).splitlines()
    assert out[0].split() == TABLE_HEADER + ["margin", "found_by"]
    # one + adds the whole list
    out = ok("select", "n=7", "-c", "+found_by,source_id", "--db", catalog.url).splitlines()
    assert out[0].split() == TABLE_HEADER + ["found_by", "source_id"]
    one_line_error(run("select", "-c", "id,+margin", "--db", catalog.url), "columns to add")
    csv_out = ok("select", "n=7", "--csv", "-c", "id,n", "--db", catalog.url).splitlines()
    assert csv_out[0] == "id,n" and len(csv_out) == 1 + 5
    r = run_many(["select", "-c", "id,colour", "--db", catalog.url])[0]
    one_line_error(r, "unknown column 'colour'")
    # the default limit of a table (not of JSON or CSV), in this process so that it can be made small
    from click.testing import CliRunner

    import packings.service.cli

    monkeypatch.setattr(packings.service.cli, "TABLE_LIMIT", 7)
    table = CliRunner().invoke(packings.service.cli.cli, ["select", "--db", catalog.url]).output.splitlines()
    assert len(table) == 1 + 7 + 1 and table[-1].startswith("7 of 18 clusters")
    as_json = CliRunner().invoke(packings.service.cli.cli, ["select", "--json", "--db", catalog.url]).output
    assert len(json.loads(as_json)) == 18


def test_what_a_column_shows_can_be_selected(catalog, stored):
    """found_by and source_id, shown by -c, are keys of a selection too."""
    seeds = {i for i, (c, _) in stored.items() if c.found_by == "seed"}
    out = ok("select", "found_by=seed", "-c", "id,found_by", "--db", catalog.url).splitlines()
    assert {int(line.split()[0]) for line in out[1:-1]} == seeds and len(seeds) == 2
    by_path = [i for i, (c, _) in stored.items() if c.n == 8 and c.found_by == "path"]
    assert ok("select", "n=8,found_by=path", "--count", "--db", catalog.url).strip() == str(len(by_path))
    assert ok("select", "n=8,found_by=catalysis", "--count", "--db", catalog.url).strip() == "0"
    source = next(c.source_id for c, _ in stored.values() if c.source_id is not None)
    expected = sum(c.source_id == source for c, _ in stored.values())
    assert ok("select", f"source_id={source}", "--count", "--db", catalog.url).strip() == str(expected)


def test_a_value_a_key_cannot_take_is_refused_with_the_values_it_can(catalog):
    """select 'lattice=bcc' selected nothing, silently: a key with a fixed set of values names them."""
    for selection, words in [
        ("lattice=bcc", ["bad value 'bcc' for lattice", "fcc, hcp, both, random, 2d, none"]),
        ("found_by=luck", ["expected one of seed, path, catalysis, close-packed"]),
        ("static=wobbly", ["hypostatic, isostatic, hyperstatic"]),
    ]:
        r = run("select", selection, "--db", catalog.url)
        one_line_error(r, *words)
        assert r.returncode == 2
    assert ok("select", "lattice=both", "--count", "--db", catalog.url).strip() != "0"


def test_select_count(catalog):
    counts = {
        "": 18,
        "n=8": 13,
        "isostatic,!singular,n>=7": 18,
        "hyperstatic": 0,
        f"run={catalog.runs[8]}": 13,
        "m=15,n=7": 5,
    }
    results = run_many(*(["select", text, "--count", "--db", catalog.url] for text in counts))
    for r, expected in zip(results, counts.values()):
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip() == str(expected), r.args


def test_select_json(catalog, stored):
    out = json.loads(ok("select", "n=7", "--json", "--db", catalog.url))
    assert [o["id"] for o in out] == [i for i, (c, _) in stored.items() if c.n == 7]
    for o in out:
        c, x = stored[o["id"]]
        assert set(TABLE_HEADER) <= set(o)
        assert (o["n"], o["contacts"], o["certificate"], o["singular"], o["min_gap"]) == (
            c.n,
            c.contacts,
            c.certificate,
            c.singular,
            c.min_gap,
        )
        assert np.array_equal(np.array(o["coords"]), x)
        assert o["contact_list"] == json.loads(c.contact_list) and len(o["contact_list"]) == c.contacts
    assert json.loads(ok("select", "n=5", "--json", "--db", catalog.url)) == []


def test_select_csv_sort_and_limit(catalog, stored):
    out = list(
        csv.DictReader(
            io.StringIO(ok("select", "n=8", "--csv", "--sort", "-min_gap", "--limit", "4", "--db", catalog.url))
        )
    )
    expected = sorted((c for c, _ in stored.values() if c.n == 8), key=lambda c: (-c.min_gap, c.id))[:4]
    assert [int(r["id"]) for r in out] == [c.id for c in expected]
    assert "coords" not in out[0] and "contact_list" not in out[0]
    assert set(TABLE_HEADER) <= set(out[0])
    assert [float(r["min_gap"]) for r in out] == [c.min_gap for c in expected]
    assert [r["certificate"] for r in out] == [c.certificate for c in expected]


SELECT_ERRORS = [
    (["n==7"], ["bad operator '=='"]),
    (["colour=red"], ["unknown key 'colour'", "known keys:"]),
    (["n=seven"], ["bad value 'seven'"]),
    (["singular<1"], ["does not apply"]),
    (["--sort", "nope"], ["unknown key 'nope'"]),
    (["--json", "--csv"], ["at most one of"]),
    (["--limit", "-1"], ["--limit"]),
    ([], ["no database at"]),  # select never creates a database
]


def test_select_errors_are_one_line(tmp_path):
    missing = f"sqlite:///{tmp_path / 'none.db'}"
    results = run_many(*(["select", *args, "--db", missing] for args, _ in SELECT_ERRORS), cwd=tmp_path)
    for r, (_, words) in zip(results, SELECT_ERRORS):
        one_line_error(r, *words)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- show


def test_show(catalog, stored):
    from packings.service.db import sessions

    cid = next(i for i, (c, _) in stored.items() if c.n == 8)
    c, x = stored[cid]
    out = ok("show", str(cid), "--db", catalog.url)
    assert out.startswith(f"cluster {cid}: n = 8, 18 contacts (3n-6+0, isostatic)")
    for name in ("certificate", "rigid_kind", "rigid_method", "margin", "min_gap", "found_in_run", "created_at"):
        assert f"\n  {name} " in out
    for row in x:  # every coordinate, exactly
        assert all(repr(float(v)) in out for v in row)
    assert f"contacts ({c.contacts}):" in out
    assert f"run {catalog.runs[8]} (n = 8, complete): expansion done" in out
    assert "\n  exact root    proved: within " in out  # regular: Kantorovich's theorem proves its root

    info = json.loads(ok("show", str(cid), "--json", "--db", catalog.url))
    assert np.array_equal(np.array(info["coords"]), x)
    assert info["exact"]["status"] == "proved" and 0 < info["exact"]["radius"] < 1e-12
    assert info["exact"]["gap"] == pytest.approx(c.min_gap, abs=1e-12)
    with sessions(catalog.engine)() as s:
        leaving = sum(t.direction != 0 for t in queries.transitions(s, source=cid))
        reaching = sum(t.direction != 0 for t in queries.transitions(s, target=cid))
    assert (info["paths_leaving"], info["paths_reaching"]) == (leaving, reaching)
    assert leaving > 0 and sum(info["leaving_by_outcome"].values()) == leaving
    assert f"paths leaving: {leaving} (" in out and f"paths reaching: {reaching} from" in out
    assert [r["run"] for r in info["runs"]] == [catalog.runs[8]]


def test_show_missing_id(catalog):
    missing, bad = run_many(["show", "9999", "--db", catalog.url], ["show", "abc", "--db", catalog.url])
    one_line_error(missing, "no cluster with id 9999")
    one_line_error(bad, "'abc'")


# --------------------------------------------------------------------------- export


def test_export_extxyz_reads_in_ase(catalog, stored, tmp_path):
    import ase.io

    path = tmp_path / "clusters.extxyz"
    out = ok("export", "--format", "extxyz", "-o", str(path), "--db", catalog.url)
    assert out.strip() == f"wrote 18 clusters (extxyz) to {path}"
    frames = ase.io.read(path, index=":")
    assert [a.info["cluster_id"] for a in frames] == list(stored)
    for atoms in frames:
        c, x = stored[int(atoms.info["cluster_id"])]
        assert np.array_equal(atoms.positions, x)
        assert len(atoms) == c.n and set(atoms.get_chemical_symbols()) == {"X"}
        assert (atoms.info["n"], atoms.info["contacts"], atoms.info["embedding"]) == (c.n, c.contacts, c.embedding)
        assert (atoms.info["singular"], atoms.info["flexes"], atoms.info["self_stresses"]) == (
            c.singular,
            c.flexes,
            c.stresses,
        )
        assert atoms.info["min_gap"] == c.min_gap
        cert = atoms.info["certificate"]  # ASE reads a value made only of digits as a number
        assert cert == c.certificate if isinstance(cert, str) else int(c.certificate) == cert
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left


def test_export_extxyz_goes_into_an_ase_database(catalog, stored, tmp_path):
    """What `ase db` users do: the facts an extended XYZ frame carries are accepted as key-value pairs
    of ASE's database as they are, and `ase db` selects on them."""
    import ase.db
    import ase.io

    path = tmp_path / "clusters.extxyz"
    ok("export", "n=8", "-o", str(path), "--db", catalog.url)
    with ase.db.connect(tmp_path / "ase.db") as db:
        for atoms in ase.io.read(path, index=":"):
            db.write(atoms, key_value_pairs=atoms.info)
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "ase",
            "db",
            str(tmp_path / "ase.db"),
            "contacts=18,n=8",
            "-c",
            "cluster_id,self_stresses",
            "--limit",
            "0",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    ids = sorted(i for i, (c, _) in stored.items() if c.n == 8 and c.contacts == 18)
    cells = [line.split("|") for line in r.stdout.splitlines()[1:] if "|" in line]
    shown = sorted(int(c[0]) for c in cells if c[0].strip().isdigit())  # the cluster_id column
    assert shown == ids and ids
    r = subprocess.run(
        [sys.executable, "-m", "ase", "convert", str(path), str(tmp_path / "converted.db")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr


def test_export_extxyz_to_stdout_is_exact(catalog, stored):
    frames = read_xyz(ok("export", "n>7", "--db", catalog.url))  # extxyz is the default
    assert len(frames) == 13
    for comment, species, x in frames:
        facts = dict(kv.split("=", 1) for kv in comment.split())
        assert facts["Properties"] == "species:S:1:pos:R:3"
        c, stored_x = stored[int(facts["cluster_id"])]
        assert facts["certificate"] == c.certificate and facts["singular"] == "TF"[not c.singular]
        assert float(facts["min_gap"]) == c.min_gap
        assert species == ["X"] * c.n
        assert np.array_equal(x, stored_x)


def test_export_xyz_is_exact(catalog, stored, tmp_path):
    path = tmp_path / "n8.xyz"  # the format follows the suffix
    ok("export", "--n", "8", "-o", str(path), "--db", catalog.url)
    frames = read_xyz(path.read_text())
    ids = [i for i, (c, _) in stored.items() if c.n == 8]
    assert [int(dict(kv.split("=", 1) for kv in f[0].split())["cluster_id"]) for f in frames] == ids
    for (comment, species, x), i in zip(frames, ids):
        assert "Properties" not in comment
        assert species == ["X"] * 8 and np.array_equal(x, stored[i][1])


def test_export_json_is_exact(catalog, stored, tmp_path):
    path = tmp_path / "all.json"
    ok("export", "--format", "json", "-o", str(path), "--db", catalog.url)
    out = json.loads(path.read_text())
    assert [o["id"] for o in out] == list(stored)
    for o in out:
        c, x = stored[o["id"]]
        assert np.array_equal(np.array(o["coords"], dtype=np.float64), x)
        assert o["contact_list"] == json.loads(c.contact_list)
        for name in (
            "n",
            "contacts",
            "embedding",
            "certificate",
            "rigid_kind",
            "rigid_method",
            "margin",
            "flexes",
            "stresses",
            "singular",
            "min_gap",
            "found_in_run",
        ):
            assert o[name] == getattr(c, name), name
        assert o["excess"] == c.contacts - (3 * c.n - 6)
    assert json.loads(ok("export", "n=5", "--format", "json", "--db", catalog.url)) == []


def test_export_replaces_a_file_whole(catalog, tmp_path):
    path = tmp_path / "out.json"
    path.write_text("old")
    ok("export", "n=7", "-o", str(path), "--db", catalog.url)
    assert len(json.loads(path.read_text())) == 5
    r = run("export", "n=7,", "-o", str(path), "--db", catalog.url)  # an error leaves the old file alone
    one_line_error(r, "empty term")
    assert len(json.loads(path.read_text())) == 5
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]


EXPORT_ERRORS = [
    (["--format", "pdb"], ["'pdb' is not one of"]),
    (["n=", "--format", "xyz"], ["missing value"]),
    (["stacking=fcc"], ["unknown key 'stacking'"]),
    ([], ["no database at"]),
]


def test_export_errors_are_one_line_and_write_nothing(tmp_path):
    db, out = f"sqlite:///{tmp_path / 'none.db'}", str(tmp_path / "out.xyz")
    results = run_many(*(["export", *args, "-o", out, "--db", db] for args, _ in EXPORT_ERRORS), cwd=tmp_path)
    for r, (_, words) in zip(results, EXPORT_ERRORS):
        one_line_error(r, *words)
    assert list(tmp_path.iterdir()) == []


def test_export_to_a_missing_directory(catalog, tmp_path):
    one_line_error(run("export", "-o", str(tmp_path / "no" / "out.xyz"), "--db", catalog.url), "cannot write")
    assert list(tmp_path.iterdir()) == []


def test_help_lists_the_keys():
    for r in run_many(["select", "--help"], ["export", "--help"]):
        assert r.returncode == 0, r.stderr
        assert "hyperstatic" in r.stdout and "run=1" in r.stdout and "min_gap" in r.stdout
