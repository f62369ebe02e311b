"""``packings audit`` (packings.service.audit) on both backends: a clean catalogue, a junk near copy, close
geometries of one contact graph, small pre-stress margins."""

from __future__ import annotations

import json

import numpy as np
import pytest

from packings.service.audit import audit, format_audit
from packings.service.db import sessions
from packings.workers.audit import RIGID, near_pairs, with_contacts_added
from packings.workers.cluster import Cluster as CoreCluster
from packings.workers.identity import certificate_key, geometry_distance
from packings.workers.params import DEFAULT, Params
from packings.workers.rigidity import PRESTRESS, Rigidity, rigidity
from tests.helpers import filled_catalog, near_misses, ok, one_line_error, two_geometries
from tests.helpers import packings as run

catalog = filled_catalog(7, 8)


def url(engine) -> str:
    return engine.url.render_as_string(hide_password=False)


def store(engine, clusters, rig=None) -> list[int]:
    """Store clusters as a finished expansion does (store.insert_or_match), with their rigidity (or ``rig``)."""
    from packings.service import store as st

    ids = []
    with sessions(engine).begin() as s:
        for c in clusters:
            r = rig or rigidity(c.coords, c.contacts, DEFAULT)
            ids.append(st.insert_or_match(s, c, r, None, DEFAULT.tol_d, found_by="path", source_id=None)[0])
    return ids


def audited(engine, n=None):
    with sessions(engine, readonly=True)() as s:
        return audit(s, n)


def real_of(junk: CoreCluster) -> CoreCluster:
    """The cluster a near miss passed by: the near miss with its near pairs added as contacts."""
    added = with_contacts_added(junk, [p.pair for p in near_pairs(junk, DEFAULT.tol_a0)], DEFAULT)
    assert added.status == RIGID
    return added.cluster


# --------------------------------------------------------------------------- a clean catalogue


def test_an_enumerated_catalogue_audits_clean(catalog):
    """n = 7 and 8 as enumerated: no near pair, no small pre-stress margin, no close geometries."""
    r = audited(catalog.engine)
    assert sorted(r.tolerances) == [7, 8]
    assert r.tolerances[8] == {"tol_a0": 1e-3, "tol_psd": 1e-5, "tol_d": 1e-5}
    assert r.near == [] and r.prestress == [] and r.close == [] and r.clean
    # every cluster of n = 7 and 8 is regular, and each is proved to stand for an exact cluster
    assert {n: (e.clusters, e.proved, e.pairs) for n, e in r.exact.items()} == {7: (5, 5, 0), 8: (13, 13, 0)}
    assert all(0 < e.max_radius < 1e-12 and 0.05 < e.min_gap < 0.052 and e.max_others == 0 for e in r.exact.values())
    assert r.unproved == [] and r.unseparated == []
    assert "n = 8: 13 of 13 proved within " in format_audit(r)
    assert format_audit(r).endswith("\nclean")
    assert audited(catalog.engine, 8).tolerances.keys() == {8}
    assert audited(catalog.engine, 9).tolerances == {}


# --------------------------------------------------------------------------- a junk near copy


def test_a_junk_near_copy_is_reported_with_the_cluster_it_copies(engine):
    """The two n = 12 near misses (stored as clusters before packings.workers.paths._endpoint re-projected) and
    the cluster they passed by: each near miss is in list (a), each of its near pairs alone and both
    together giving that stored cluster; the real cluster is not in it."""
    junk = [m["cluster"] for m in near_misses()]
    real = real_of(junk[0])
    real_id, *junk_ids = store(engine, [real, *junk])
    assert len({real_id, *junk_ids}) == 3  # three rows: the near misses are not the real cluster
    r = audited(engine)
    assert r.near_clusters == sorted(junk_ids)
    assert r.near_copies == {j: [real_id] for j in junk_ids}
    for j in junk_ids:
        rows = [x for x in r.near if x.id == j]
        assert len(rows) == 3 and all(x.status == RIGID and x.match == real_id and x.new_contacts == 33 for x in rows)
        assert [len(x.pairs) for x in rows] == [1, 1, 2] and all(2e-4 < x.gap < 2.5e-4 for x in rows)
        assert all(x.n == 12 and x.contacts == 31 for x in rows)
    # the two near misses are also two geometries of one contact graph 3.4e-5 apart: list (c)
    assert [(c.a, c.b) for c in r.close] == [tuple(junk_ids)] and 1e-5 < r.close[0].distance < 1e-4
    assert not r.clean
    text = format_audit(r)
    assert "near pairs (gap < tol_a0): 2 clusters, 6 additions" in text
    # and no root of their contact equations is proved near either (list (d)); the real cluster's is
    assert [(x.id, x.status) for x in r.unproved] == [(j, "too-far") for j in junk_ids]
    assert r.exact[12].clusters == 3 and r.exact[12].proved == 1
    assert text.splitlines()[-1] == (
        "not clean: 2 clusters with a near pair, 2 of them near copies of stored "
        f"clusters: {junk_ids[0]} -> {real_id}, {junk_ids[1]} -> {real_id}; "
        "1 pair of close geometries; 2 clusters with no flex and no root proved"
    )


def test_a_near_pair_whose_cluster_is_not_stored_says_so(engine):
    (junk_id,) = store(engine, [near_misses()[0]["cluster"]])
    r = audited(engine)
    assert [x.id for x in r.near] == [junk_id] * 3
    assert all(x.status == RIGID and x.match is None for x in r.near) and r.near_copies == {}
    assert "not stored" in format_audit(r)
    assert [x.id for x in r.unproved] == [junk_id]
    assert format_audit(r).splitlines()[-1] == (
        "not clean: 1 cluster with a near pair, 0 of them near copies of "
        "stored clusters; 1 cluster with no flex and no root proved"
    )


# --------------------------------------------------------------------------- close geometries


def test_two_geometries_of_one_graph_1e4_apart_are_reported(engine):
    """A real cluster and a copy with one sphere moved by 1e-4 (the same contacts): two rows of one
    certificate, in list (c) with their distance; the two genuine n = 11 geometries of one graph are not."""
    real = real_of(near_misses()[0]["cluster"])
    x = real.coords.copy()
    x[5] += [0.0, 1e-4, 0.0]
    moved = CoreCluster(x, real.contacts)
    a, b, *_ = ids = store(engine, [real, moved, *two_geometries()])
    assert len(set(ids)) == 4 and certificate_key(real) == certificate_key(moved)
    r = audited(engine)
    assert [(c.n, c.a, c.b) for c in r.close] == [(12, a, b)]
    (c,) = r.close
    assert c.distance == pytest.approx(geometry_distance(moved, real), rel=1e-9)
    assert 1e-5 < c.distance < 1e-4 + 1e-12 and c.certificate == certificate_key(real)
    assert r.near == [] and not r.clean
    assert "close geometries of one contact graph (< 100 tol_d): 1 pair" in format_audit(r)
    # the moved copy's root is the real cluster's: list (d) cannot tell them apart either
    assert [(u.a, u.b) for u in r.unseparated] == [(a, b)] and r.unproved == []
    assert format_audit(r).splitlines()[-1] == "not clean: 1 pair of close geometries; 1 pair of roots not told apart"
    assert audited(engine, 11).close == [] and audited(engine, 11).clean  # 0.79 apart


# --------------------------------------------------------------------------- exact clusters


def test_a_regular_cluster_far_from_any_exact_one_and_a_copy_within_the_radius_are_reported(engine):
    """List (d): a regular n = 11 cluster with its spheres moved 0.05 at random (no exact cluster proved:
    too far), and one moved 5e-5 (proved, but its exact cluster may be the original's: not told apart),
    beside the two genuine geometries of one n = 11 graph (proved and told apart)."""
    a, b = two_geometries()
    rng = np.random.default_rng(0)
    far = CoreCluster(a.coords + 0.05 * rng.normal(size=a.coords.shape), a.contacts)
    x = a.coords.copy()
    x[3] += 5e-5
    near = CoreCluster(x, a.contacts)
    ida, idb, idfar, idnear = store(engine, [a, b, far, near])
    r = audited(engine)
    e = r.exact[11]
    assert (e.clusters, e.proved, e.pairs) == (4, 3, 3)
    assert [(x.id, x.status) for x in r.unproved] == [(idfar, "too-far")] and r.unproved[0].h > 0.5
    (u,) = r.unseparated
    assert (u.a, u.b) == (ida, idnear) and u.bound <= u.radii and u.certificate == certificate_key(a)
    assert not r.clean
    text = format_audit(r)
    assert "n = 11: 3 of 4 proved within " in text and "too-far" in text
    assert text.splitlines()[-1].endswith("1 cluster with no flex and no root proved; 1 pair of roots not told apart")
    d = r.to_dict()
    assert d["exact"]["11"]["proved"] == 3 and d["unproved"][0]["id"] == idfar and d["unseparated"][0]["b"] == idnear


# --------------------------------------------------------------------------- pre-stress margins


def test_small_prestress_margins_against_the_runs_tol_psd(engine):
    """List (b) holds the pre-stress clusters whose stored margin is below 10 tol_psd, tol_psd read from
    the run of that n; first-order rigid clusters are never in it."""
    from packings.service import store as st

    real = real_of(near_misses()[0]["cluster"])
    small, large = (Rigidity(True, PRESTRESS, 1, 1, "single-flex", margin) for margin in (5e-5, 2e-4))
    (small_id,) = store(engine, [real], small)
    (large_id,) = store(engine, [two_geometries()[0]], large)
    (first_order,) = store(engine, [two_geometries()[1]])
    r = audited(engine)
    assert [(x.id, x.margin, x.method) for x in r.prestress] == [(small_id, 5e-5, "single-flex")]
    assert r.prestress[0].tol_psd == DEFAULT.tol_psd and r.clean  # (b) does not make it unclean
    assert format_audit(r).splitlines()[-1] == "clean (1 small pre-stress margin)"
    st.start_run(sessions(engine), 12, Params(tol_psd=1e-6), "test:0:audit")  # margins below 1e-5 only
    st.start_run(sessions(engine), 11, Params(tol_psd=1e-4), "test:0:audit")  # margins below 1e-3
    r = audited(engine)
    assert r.tolerances[12]["tol_psd"] == 1e-6 and r.tolerances[11]["tol_psd"] == 1e-4
    assert [x.id for x in r.prestress] == [large_id]
    assert first_order not in [x.id for x in r.prestress]


# --------------------------------------------------------------------------- the command


def test_audit_command_text_and_json(catalog):
    text = ok("audit", "--db", catalog.url)
    assert [line.split(":")[0] for line in text.splitlines() if ": " in line and not line.startswith("audit")] == [
        "near pairs (gap < tol_a0)",
        "pre-stress margins (< 10 tol_psd)",
        "close geometries of one contact graph (< 100 tol_d)",
        "exact clusters (Kantorovich; clusters with no flex)",
    ]
    assert text.splitlines()[-1] == "clean"
    d = json.loads(ok("audit", "--n", "7", "--json", "--db", catalog.url))
    exact = d.pop("exact")
    assert d == {
        "tolerances": {"7": {"tol_a0": 1e-3, "tol_psd": 1e-5, "tol_d": 1e-5}},
        "near": [],
        "prestress": [],
        "close": [],
        "unproved": [],
        "unseparated": [],
        "near_copies": {},
        "clean": True,
    }
    assert list(exact) == ["7"] and exact["7"]["clusters"] == exact["7"]["proved"] == 5


def test_audit_command_reports_a_near_copy_and_exits_0(engine):
    junk = near_misses()[0]["cluster"]
    real_id, junk_id = store(engine, [real_of(junk), junk])
    r = run("audit", "--json", "--db", url(engine))
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["clean"] is False and d["near_copies"] == {str(junk_id): [real_id]}
    assert {row["match"] for row in d["near"]} == {real_id} and all(row["id"] == junk_id for row in d["near"])
    assert json.dumps(d)  # every value JSON-able (floats, ints, lists)
    assert isinstance(d["near"][0]["gap"], float) and isinstance(d["near"][0]["pairs"], list)
    r = run("audit", "--db", url(engine))
    assert r.returncode == 0 and f"{junk_id} -> {real_id}" in r.stdout.splitlines()[-1]


def test_audit_command_on_no_database_is_one_line(tmp_path):
    one_line_error(run("audit", "--db", f"sqlite:///{tmp_path / 'none.db'}"), "no database")
