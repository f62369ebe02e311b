"""The endpoint rule (docs/method.md), on the real n = 12 clusters that exposed it.

tests/data/n12_junk.json holds three clusters an n = 12 run stored before the rule, the paths that
produced them and the clusters they stand for: two second solutions of their contact equations
found by an endpoint projection that went far from the path, and one point on a curve of singular
points whose pre-stress margin was noise.
"""

from __future__ import annotations

import json
from itertools import combinations
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from packings.workers import kernels
from packings.workers.cluster import Cluster
from packings.workers.expand import PathStart, _attempts
from packings.workers.identity import certificate, geometry_distance, same_geometry
from packings.workers.params import DEFAULT as P
from packings.workers.paths import PROJECTION_FAILED, RIGID, close_pairs, near_pairs, resolve_near_pairs
from packings.workers.rigidity import contact_triangle, on_a_curve, rigidity
from tests.helpers import transformed

DATA = json.loads((Path(__file__).parents[1] / "data" / "n12_junk.json").read_text())
FAR, NEAR_COPY, ON_A_CURVE = DATA["paths"]
N10 = json.loads((Path(__file__).parents[1] / "data" / "clusters_n10.json").read_text())


def cluster(row: dict) -> Cluster:
    return Cluster(np.array(row["coords"]), tuple(map(tuple, row["contacts"])))


def framed(c: Cluster) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x (flat, in the frame of the first contact triangle), the contacts and the free coordinates."""
    edges = c.edges()
    tri = contact_triangle(edges)
    return kernels.to_frame(c.coords, tri).ravel(), edges, kernels.free_coordinates(c.n, tri)


def follow(case: dict):
    source = cluster(case["source"])
    broken = tuple(map(tuple, case["broken"]))
    # the recorded direction is relative to the tangent of an SVD of what is left: the reference's attempts
    starts = [s for s in _attempts(source, P, first_order=False) if isinstance(s, PathStart)]
    (start,) = [s for s in starts if s.broken_contacts == broken and s.direction == case["direction"]]
    return start.follow(P)


def test_the_stored_clusters_are_what_the_data_says():
    """Each was stored with a pair within a few tol_a of touching, or a margin near tol_psd."""
    for case in (FAR, NEAR_COPY):
        c = cluster(case["stored"])
        assert P.tol_a < c.min_gap() < 1e-4
    assert ON_A_CURVE["stored"]["margin"] < 3 * P.tol_psd


def test_a_path_whose_contact_is_not_resolved_within_tol_a0_ends_without_a_cluster():
    """The path from the source passes within 1e-5 of two contacts at once; projecting onto them
    moves spheres by 7e-3, far beyond tol_a0: the endpoint is not resolved, and nothing is stored
    (before, a projection from 1e-3 away went 0.27 and stored a second solution)."""
    end = follow(FAR)
    assert end.outcome == PROJECTION_FAILED
    assert end.coords is None


def test_a_path_that_ended_at_a_near_copy_ends_at_the_cluster_it_stands_for():
    end = follow(NEAR_COPY)
    assert end.outcome == RIGID
    c = Cluster(end.coords, end.contacts)
    target = cluster(NEAR_COPY["stands_for"])
    assert c.m == target.m == 32
    assert certificate(c) == certificate(target) and same_geometry(c, target, P.tol_d)
    assert not near_pairs(end.coords.ravel(), end.contacts, P.tol_a0).size


def test_a_path_onto_a_curve_of_singular_points_ends_without_a_cluster():
    """The margin alone said rigid.  On a curve there is no isolated point for the refinement along the
    flexes to converge to: it slides along the curve (1.2e-2 here), beyond tol_a0, so no projection
    counts, there or after walking to the contact."""
    end = follow(ON_A_CURVE)
    assert end.outcome == PROJECTION_FAILED and end.coords is None
    x, edges, free = framed(cluster(ON_A_CURVE["stored"]))
    y = kernels.refine_singular(x, edges, free)
    assert np.abs(y - x).max() > P.tol_a0


def test_a_stored_near_copy_resolves_to_the_cluster_with_its_near_pairs():
    for case, m in ((FAR, 33), (NEAR_COPY, 32)):
        x, edges, free = framed(cluster(case["stored"]))
        xr, contacts, rig = resolve_near_pairs(x, cluster(case["stored"]).contacts, free, P)
        c = Cluster(xr.reshape(-1, 3), contacts)
        assert rig.rigid and c.m == m
        assert same_geometry(c, cluster(case["stands_for"]), P.tol_d)
        f = kernels.residual(xr, np.array(contacts, dtype=np.int64))
        assert float(f @ f) < P.tol


def test_a_cluster_without_near_pairs_is_not_resolved():
    for raw in N10.values():
        c = Cluster.from_dict(raw)
        x, edges, free = framed(c)
        assert c.min_gap() > P.tol_a0
        assert resolve_near_pairs(x, c.contacts, free, P) is None


def test_a_projection_that_would_move_a_sphere_beyond_tol_a0_does_not_count():
    """close_pairs from the stored near copy with a tol_a0 below its distance to the cluster it stands for."""
    c = cluster(NEAR_COPY["stored"])
    x, edges, free = framed(c)
    near = near_pairs(x, c.contacts, P.tol_a0)
    assert close_pairs(x, edges, near, free, P) is not None
    assert close_pairs(x, edges, near, free, P.with_(tol_a0=1e-5)) is None  # it moves spheres 8.3e-5


def test_the_point_on_a_curve_is_found_on_a_curve_and_genuine_prestress_clusters_are_not():
    c = cluster(ON_A_CURVE["stored"])
    x, edges, free = framed(c)
    ns = kernels.null_spaces(x, edges, free, P.tol_n)
    assert ns.V.shape[1] == 1 and on_a_curve(x, edges, free, ns.V, P)
    verdict = rigidity(c.coords, c.contacts, P)
    assert not verdict.rigid and verdict.method in ("probe", "unresolved")
    for name in ("n10_m24_prestress", "n10_m23_prestress"):
        g = Cluster.from_dict(N10[name])
        x, edges, free = framed(g)
        ns = kernels.null_spaces(x, edges, free, P.tol_n)
        assert ns.V.shape[1] >= 1 and not on_a_curve(x, edges, free, ns.V, P)
        assert rigidity(g.coords, g.contacts, P).rigid


seeds = st.integers(0, 2**32 - 1)


@settings(max_examples=10, deadline=None)
@given(seeds, st.booleans())
def test_the_rule_is_invariant_under_rotation_reflection_and_relabelling(seed, reflect):
    for case in (FAR, NEAR_COPY):
        c = transformed(cluster(case["stored"]), seed, reflect)
        x, edges, free = framed(c)
        xr, contacts, rig = resolve_near_pairs(x, c.contacts, free, P)
        assert rig.rigid and same_geometry(Cluster(xr.reshape(-1, 3), contacts), cluster(case["stands_for"]), P.tol_d)
    c = transformed(cluster(ON_A_CURVE["stored"]), seed, reflect)
    assert not rigidity(c.coords, c.contacts, P).rigid  # the margin is noise, the verdict is not


def test_two_copies_of_a_singular_cluster_agree_once_refined_along_their_flexes():
    first, second = cluster(DATA["copies"]["first"]), cluster(DATA["copies"]["second"])
    assert certificate(first) == certificate(second) and not same_geometry(first, second, P.tol_d)  # as stored
    refined = []
    for c in (first, second):
        x, edges, free = framed(c)
        y = kernels.refine_singular(x, edges, free)
        f = kernels.residual(y, edges)
        assert float(f @ f) <= float(kernels.residual(x, edges) @ kernels.residual(x, edges))
        refined.append(Cluster(y.reshape(-1, 3), c.contacts))
    assert same_geometry(refined[0], refined[1], P.tol_d / 10)  # before: 1.08 tol_d apart


SINGULAR_13 = json.loads((Path(__file__).parents[1] / "data" / "n13_singular.json").read_text())["clusters"][0]


def copies_along_the_flexes(c: Cluster, count: int, seed: int = 0) -> list[np.ndarray]:
    """``count`` copies of ``c`` (framed) as an endpoint projection leaves them: moved 1e-5 ... 3e-3 along a
    random combination of its flexes, then projected onto its contacts and polished, not refined."""
    x, edges, free = framed(c)
    flexes = kernels.null_spaces(x, edges, free, P.tol_n).V
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        d = flexes @ rng.normal(size=flexes.shape[1])
        y = x + 10 ** rng.uniform(-5, -2.5) * d / np.abs(d).max()
        out.append(kernels.project(y, edges, free, polish=True, **P.newton()).x)
    return out


def test_copies_of_an_n13_singular_cluster_with_a_small_margin_agree_once_refined():
    """Two flexes, one stress, margin 4e-3: the Newton step of sum f^2 alone left copies up to 9.6e-5
    apart (the curved valley along the flexes halved its steps to nothing); with the return to the
    valley floor after each step they agree within 5e-7."""
    c = cluster(SINGULAR_13)
    assert (SINGULAR_13["flexes"], SINGULAR_13["stresses"]) == (2, 1) and SINGULAR_13["margin"] < 5e-3
    x, edges, free = framed(c)
    polished = copies_along_the_flexes(c, 6)
    spread = max(geometry_distance(c, Cluster(y.reshape(-1, 3), c.contacts)) for y in polished)
    assert spread > P.tol_d  # as an endpoint projection leaves them: further apart than tol_d
    refined = [Cluster(kernels.refine_singular(y, edges, free).reshape(-1, 3), c.contacts) for y in [x, *polished]]
    for r in refined:
        f = kernels.residual(r.coords.ravel(), edges)
        assert float(f @ f) < 1e-28
    assert max(geometry_distance(a, b) for a, b in combinations(refined, 2)) < P.tol_d / 10


@settings(max_examples=5, deadline=None)
@given(seeds, st.booleans())
def test_refining_commutes_with_rotation_reflection_and_relabelling(seed, reflect):
    c = cluster(SINGULAR_13)
    (y,) = copies_along_the_flexes(c, 1, seed % 1000)
    copy = Cluster(y.reshape(-1, 3), c.contacts)
    moved = transformed(copy, seed, reflect)
    refined = []
    for a in (copy, moved):
        x, edges, free = framed(a)
        refined.append(Cluster(kernels.refine_singular(x, edges, free).reshape(-1, 3), a.contacts))
    assert geometry_distance(refined[0], refined[1]) < P.tol_d / 10
    assert geometry_distance(refined[0], c) < P.tol_d / 2


def test_an_endpoint_whose_refinement_leaves_tol_a0_walks_to_the_contact_and_is_not_a_copy():
    """tests/data/n13_refine_far.json: a path that stopped 9.8e-4 from a singular 32-contact cluster,
    whose polished endpoint refined to a point just beyond tol_a0 from the stopping point.  Keeping the
    polished point there stored a second copy of the cluster (residuals 2.3e-10, 1.46e-5 away); now
    that projection does not count, the path walks to the contact, and its endpoint is the cluster
    itself, refined to round-off."""
    d = json.loads((Path(__file__).parents[1] / "data" / "n13_refine_far.json").read_text())
    parent, target = cluster(d["parent"]), cluster(d["cluster"])
    broken = tuple(map(tuple, d["broken"]))
    ends = [a.follow(P) for a in _attempts(parent, P) if isinstance(a, PathStart) and a.broken_contacts == broken]
    reached = [Cluster(e.coords, e.contacts) for e in ends if e.outcome == RIGID and len(e.contacts) == target.m]
    assert reached
    for r in reached:
        f = kernels.residual(r.coords.ravel(), r.edges())
        assert np.abs(f).max() < 1e-14
        assert geometry_distance(r, target) < P.tol_d / 10


def test_refining_a_regular_cluster_leaves_it_where_it_is():
    c = cluster(NEAR_COPY["stands_for"])
    x, edges, free = framed(c)
    assert np.abs(kernels.refine_singular(x, edges, free) - x).max() < 1e-12


def test_a_prestress_margin_the_coordinates_do_not_resolve_is_undecided():
    from packings.workers.rigidity import UNDECIDED, margin_uncertainty

    for row in DATA["unresolved"]["clusters"]:
        c = cluster(row)
        verdict = rigidity(c.coords, c.contacts, P)
        assert not verdict.rigid and verdict.kind == UNDECIDED and verdict.method == "unresolved"
        x, edges, free = framed(c)
        assert verdict.margin < P.tol_psd + margin_uncertainty(x, edges, verdict.margin)
    for name in ("n10_m24_prestress", "n10_m23_prestress"):  # genuine, polished: resolved by far
        g = Cluster.from_dict(N10[name])
        verdict = rigidity(g.coords, g.contacts, P)
        x, edges, free = framed(g)
        assert verdict.rigid and verdict.margin > 100 * (P.tol_psd + margin_uncertainty(x, edges, verdict.margin))
