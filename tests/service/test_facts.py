"""The facts of every cluster (issue 4): computed when it is stored or by the
backfill, queryable by selection, summed up by ``packings stats``, carried by
the exports; on both backends."""

from __future__ import annotations

import json
import math
from collections import Counter

import numpy as np
import pytest
from sqlalchemy import select, text

from packings.service import queries
from packings.service.models import ClusterRow
from packings.workers.classify import lattice_type, static_class
from packings.workers.cluster import Cluster as CoreCluster
from packings.workers.params import DEFAULT
from tests.helpers import filled_catalog, ok, one_line_error, run_many
from tests.helpers import packings as run

catalog = filled_catalog(7, 8)

H = math.sqrt(2.0 / 3.0)
A1, A2 = np.array([1.0, 0.0, 0.0]), np.array([0.5, math.sqrt(3.0) / 2.0, 0.0])
B, C = (A1 + A2) / 3.0, 2.0 * (A1 + A2) / 3.0


def _core(points) -> CoreCluster:
    return CoreCluster.from_coords(np.array(points, dtype=np.float64))


def cuboctahedron() -> CoreCluster:
    """13 spheres of fcc: a hexagon around a centre (layer A), a triangle above (B) and one below (C)."""
    middle = [np.zeros(3), A1, -A1, A2, -A2, A1 - A2, A2 - A1]
    up = [B + [0, 0, H], B - A1 + [0, 0, H], B - A2 + [0, 0, H]]
    down = [C - A1 - A2 - [0, 0, H], C - A1 - [0, 0, H], C - A2 - [0, 0, H]]
    return _core(middle + up + down)


def anticuboctahedron() -> CoreCluster:
    """13 spheres of hcp: as the cuboctahedron with the lower triangle in position B as well."""
    middle = [np.zeros(3), A1, -A1, A2, -A2, A1 - A2, A2 - A1]
    up = [B + [0, 0, H], B - A1 + [0, 0, H], B - A2 + [0, 0, H]]
    down = [p - [0, 0, 2 * H] for p in up]
    return _core(middle + up + down)


def octahedron() -> CoreCluster:
    """6 spheres: a triangle in layer A and the opposite triangle in C: a fragment of fcc and of hcp."""
    return _core([np.zeros(3), A1, A2, C + [0, 0, H], C - A1 + [0, 0, H], C - A2 + [0, 0, H]])


def pentagonal_bipyramid() -> CoreCluster:
    r = 1.0 / (2.0 * math.sin(math.pi / 5.0))
    ring = [[r * math.cos(2 * math.pi * k / 5), r * math.sin(2 * math.pi * k / 5), 0.0] for k in range(5)]
    z = math.sqrt(1.0 - r * r)
    return _core(ring + [[0.0, 0.0, z], [0.0, 0.0, -z]])


CONSTRUCTED = {"fcc": cuboctahedron, "hcp": anticuboctahedron, "none": pentagonal_bipyramid}


def store_clusters(engine, clusters) -> list[int]:
    """Store clusters the way a finished expansion does (store.insert_or_match)."""
    from packings.service import store
    from packings.service.db import sessions
    from packings.workers.rigidity import rigidity

    Session_ = sessions(engine)
    ids = []
    with Session_.begin() as s:
        for c in clusters:
            ids.append(
                store.insert_or_match(
                    s, c, rigidity(c.coords, c.contacts, DEFAULT), None, DEFAULT.tol_d, found_by="seed", source_id=None
                )[0]
            )
    return ids


def url(engine) -> str:
    return engine.url.render_as_string(hide_password=False)


# --------------------------------------------------------------------------- stored facts


def test_the_constructed_clusters_are_what_they_claim():
    for label, build in {**CONSTRUCTED, "both": octahedron}.items():
        c = build()
        assert c.min_distance() > 1 - 1e-12
        assert (lattice_type(c.coords, c.contacts) or "none") == label
    assert cuboctahedron().m == anticuboctahedron().m == 36  # 12 radial + 24 on the surface
    assert pentagonal_bipyramid().m == 15


def test_facts_are_stored_selected_and_exported(engine, tmp_path):
    import ase.io

    ids = dict(zip(CONSTRUCTED, store_clusters(engine, [build() for build in CONSTRUCTED.values()])))
    u = url(engine)
    for label, cid in ids.items():
        rec = json.loads(ok("show", str(cid), "--json", "--db", u))
        assert rec["lattice"] == label and rec["close_packed"] == (label != "none")
        assert rec["geometries"] == 1
    assert rec["static"] == "isostatic" and rec["excess"] == 0  # the bipyramid: 15 = 3*7-6
    fcc = json.loads(ok("select", "lattice=fcc", "--json", "--db", u))
    assert [o["id"] for o in fcc] == [ids["fcc"]]
    counts = {
        "close_packed": 2,
        "!close_packed": 1,
        "fcc": 1,
        "hcp": 1,
        "lattice=none": 1,
        "hyperstatic": 2,
        "static=hyperstatic,lattice=hcp": 1,
        "n=13,close_packed,contacts=36": 2,
        "geometries=1": 3,
    }
    for (sel, expected), r in zip(counts.items(), run_many(*(["select", k, "--count", "--db", u] for k in counts))):
        assert r.returncode == 0, r.stderr
        assert int(r.stdout) == expected, sel
    path = tmp_path / "cp.extxyz"
    ok("export", "close_packed", "-o", str(path), "--db", u)
    frames = ase.io.read(path, index=":")
    assert sorted(a.info["lattice"] for a in frames) == ["fcc", "hcp"]
    for a in frames:
        assert a.info["static"] == "hyperstatic" and a.info["excess"] == 3 and a.info["close_packed"] is True
        assert a.info["geometries"] == 1 and a.info["n"] == 13


def test_two_geometries_of_one_contact_graph_are_counted(engine):
    """The one n = 11 contact graph with two rigid geometries (found by ``packings enumerate 11``):
    the same certificate, different clusters, each first-order rigid; stored, they are one adjacency
    matrix with 2 geometries."""
    from pathlib import Path

    from packings.workers.identity import certificate_key, same_geometry
    from packings.workers.rigidity import rigidity

    data = json.loads((Path(__file__).parents[1] / "data" / "n11_two_geometries.json").read_text())
    a, b = (CoreCluster(np.array(c["coords"]), tuple(map(tuple, c["contacts"]))) for c in data["clusters"])
    assert a.n == b.n == 11 and a.m == b.m == 27
    assert certificate_key(a) == certificate_key(b) and not same_geometry(a, b, DEFAULT.tol_d)
    for c in (a, b):
        assert min(c.min_distance(), 1.0) > 1 - DEFAULT.tol_a
        assert rigidity(c.coords, c.contacts, DEFAULT).rigid
    ids = store_clusters(engine, [a, b, octahedron()])
    u = url(engine)
    assert sorted(o["id"] for o in json.loads(ok("select", "geometries=2", "--json", "--db", u))) == sorted(ids[:2])
    (n11,) = json.loads(ok("stats", "--n", "11", "--json", "--db", u))
    assert n11["multi_embedding"] == {"2": 1} and n11["total"] == 2
    text = ok("stats", "--n", "11", "--db", u)
    assert "geometries  adjacency matrices\n         2                   1" in text
    # two clusters and no run: far from the paper's table, and said to be partial
    assert (
        "fewer than the paper: 0 with 25 contacts (the paper 2), 0 with 26 contacts (the paper 18), 2 with 27 "
        "contacts (the paper 1618)"
        in text
        and text.count("(partial") == 2
    )
    (n6,) = json.loads(ok("stats", "--n", "6", "--json", "--db", u))
    assert n6["multi_embedding"] == {} and n6["lattice"] == {"both": 1}


# --------------------------------------------------------------------------- a real catalogue


@pytest.fixture(scope="module")
def rows(catalog):
    from packings.service.db import sessions

    with sessions(catalog.engine)() as s:
        clusters = s.execute(select(ClusterRow).order_by(ClusterRow.id)).scalars().all()
        transitions = list(queries.transitions(s))
        s.expunge_all()
    return clusters, transitions


def test_every_stored_cluster_has_its_facts(rows):
    clusters, _ = rows
    assert clusters
    for c in clusters:
        core = c.to_core()
        assert c.lattice == (lattice_type(core.coords, core.contacts) or "none")
        assert c.min_gap == pytest.approx(core.min_gap(), abs=0)


def test_stats_json_agrees_with_the_rows(catalog, rows, paper_counts):
    clusters, transitions = rows
    by_id = {c.id: c for c in clusters}
    out = {d["n"]: d for d in json.loads(ok("stats", "--json", "--db", catalog.url))}
    assert sorted(out) == [7, 8]
    for n, d in out.items():
        mine = [c for c in clusters if c.n == n]
        by_contacts = Counter(c.contacts for c in mine)
        assert d["total"] == len(mine) and d["by_contacts"] == {str(m): k for m, k in sorted(by_contacts.items())}
        assert d["singular"] == sum(c.singular for c in mine)
        assert d["singular_by_contacts"] == {
            str(m): k for m, k in sorted(Counter(c.contacts for c in mine if c.singular).items())
        }
        statics = Counter(static_class(c.n, c.contacts) for c in mine)
        assert (d["hypostatic"], d["isostatic"], d["hyperstatic"]) == (
            statics["hypostatic"],
            statics["isostatic"],
            statics["hyperstatic"],
        )
        cp = [c for c in mine if c.lattice != "none"]
        assert d["close_packed"] == len(cp) and d["lattice"] == dict(sorted(Counter(c.lattice for c in cp).items()))
        assert d["close_packed_by_contacts"] == {str(m): k for m, k in sorted(Counter(c.contacts for c in cp).items())}
        per_graph = Counter(Counter(c.certificate for c in mine).values())
        assert d["multi_embedding"] == {str(k): v for k, v in sorted(per_graph.items()) if k > 1}
        gaps = sorted((c.min_gap, c.id) for c in mine if c.min_gap is not None)
        assert d["min_gap"] == gaps[0][0]
        assert [(g["min_gap"], g["id"]) for g in d["smallest_gaps"]] == gaps[:10]
        paths = [t for t in transitions if t.direction != 0 and by_id[t.source_id].n == n]
        assert d["paths"] == len(paths) > 0
        assert d["circular_paths"] == sum(t.outcome == "circular" for t in paths) == 0  # no circle below n = 10
        assert d["rearranged_paths"] == sum(t.outcome == "rearranged" for t in paths) > 0
        reached = {t.target_id for t in transitions if t.direction != 0 and t.target_id not in (None, t.source_id)}
        assert d["unreached"] == [c.id for c in mine if c.id not in reached]
        assert d["fit"]["b"] > 0 and d["fit"]["predicted"] == pytest.approx(d["fit"]["b"] * math.factorial(n - 5))
        assert d["paper"]["by_contacts"] == paper_counts["clusters_by_contacts"][str(n)] == d["by_contacts"]
        assert d["paper"]["same"] is True and d["paper"]["total"] == paper_counts["totals"][str(n)]
    assert out[7]["total"] == 5 and out[8]["total"] == 13


def test_stats_prints_the_tables(catalog):
    out = ok("stats", "--db", catalog.url)
    for words in (
        "n = 7: 5 rigid clusters",
        "n = 8: 13 rigid clusters",
        "singular",
        "close-packed",
        "adjacency matrices with more than one geometry",
        "smallest gap",
        "smallest gaps",
        "circular paths (back to every sphere's place): 0",
        "paths to a permutational isomer of their start:",
        "fit of the totals to b·(n−5)!",
        "contacts  3n-6+  clusters  paper  singular",
        "     18     +0        13     13",
        "as the paper at every number of contacts: 5 (Holmes-Cerfon",
        "as the paper at every number of contacts: 13 (Holmes-Cerfon",
    ):
        assert words in out, words


def test_path_keys_agree_with_the_transitions(catalog, rows):
    clusters, transitions = rows
    moving = [t for t in transitions if t.direction != 0]
    out = Counter(t.source_id for t in moving)
    into = Counter(t.target_id for t in moving if t.target_id is not None and t.target_id != t.source_id)
    circ = Counter(t.source_id for t in moving if t.outcome == "circular")
    rearranged = Counter(t.source_id for t in moving if t.outcome == "rearranged")
    records = json.loads(ok("select", "--json", "--db", catalog.url))
    assert len(records) == len(clusters)
    sel = {
        "paths_out>0": sum(1 for c in clusters if out[c.id] > 0),
        "circular>0": sum(1 for c in clusters if circ[c.id] > 0),
        "rearranged>1": sum(1 for c in clusters if rearranged[c.id] > 1),
        "!reached": sum(1 for c in clusters if into[c.id] == 0),
        "paths_in>=3": sum(1 for c in clusters if into[c.id] >= 3),
    }
    for (s, expected), r in zip(sel.items(), run_many(*(["select", s, "--count", "--db", catalog.url] for s in sel))):
        assert r.returncode == 0, r.stderr
        assert int(r.stdout) == expected, s
    top = json.loads(ok("select", "--sort", "-paths_in", "--limit", "1", "--json", "--db", catalog.url))[0]
    assert into[top["id"]] == max(into.values())


# --------------------------------------------------------------------------- older databases


def test_upgrade_from_0001_backfills_the_facts(db_url):
    from packings.service.db import head_revision, migrate, open_database

    engine = open_database(db_url, create=True)
    ids = store_clusters(engine, [cuboctahedron(), pentagonal_bipyramid()])
    migrate(engine, "0001", down=True)  # back to the schema before the facts
    engine.dispose()
    one_line_error(run("stats", "--db", db_url), "packings db upgrade")
    out = ok("db", "upgrade", "--db", db_url)
    assert head_revision() in out and "computed the facts of 2 clusters" in out
    engine = open_database(db_url)
    with engine.connect() as c:
        got = dict(c.execute(text("SELECT id, lattice FROM clusters")).all())
    assert got == {ids[0]: "fcc", ids[1]: "none"}
    with engine.begin() as c:
        c.execute(text("UPDATE clusters SET lattice = NULL WHERE id = :i"), {"i": ids[1]})
    out = ok("stats", "--db", db_url)
    assert "1 cluster is not classified yet" in out
    assert ok("db", "backfill", "--db", db_url).strip() == "computed the facts of 1 cluster"
    assert ok("db", "backfill", "--db", db_url).strip() == ""  # nothing left to do
    assert ok("db", "backfill", "--all", "--db", db_url).strip() == "computed the facts of 2 clusters"
    with engine.connect() as c:
        assert dict(c.execute(text("SELECT id, lattice FROM clusters")).all()) == got
    engine.dispose()
