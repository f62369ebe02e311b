"""Tests of packings.workers.exact: Kantorovich's theorem on the contact equations, roots told apart, and the
endpoint rule that asks for it (packings.workers.paths.endpoint_rigidity)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from packings.workers import kernels
from packings.workers.cluster import Cluster
from packings.workers.exact import (
    GAP,
    NOT_RIGID,
    PROVED,
    SINGULAR,
    TOO_FAR,
    distance_lower_bound,
    exact_cluster,
    kantorovich,
    not_told_apart,
)
from packings.workers.identity import _canonical
from packings.workers.params import DEFAULT
from packings.workers.rigidity import contact_triangle
from tests.helpers import CLUSTERS, DATA, SETTINGS, catalogue, seeds, transformed, two_geometries


def regular(n: int) -> list[Cluster]:
    """The regular clusters (3n - 6 contacts, first-order rigid) of n, as enumerated."""
    from packings.workers.rigidity import rigidity

    out = [c for c in catalogue(n).clusters if c.m == 3 * n - 6]
    return [c for c in out if rigidity(c.coords, c.contacts, DEFAULT).flexes == 0]


def newton_root(c: Cluster) -> np.ndarray:
    """The root Newton's method reaches from ``c``'s coordinates on the square system exact_cluster
    analyses (triangle pinned, in its frame): plain steps, no cap on their length, as Kantorovich's theorem
    says it converges."""
    from packings.workers.rigidity import contact_triangle

    tri = contact_triangle(c.edges())
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(c.n, tri)
    for _ in range(60):
        f = kernels.residual_numpy(x, c.edges())
        x[free] -= np.linalg.solve(2.0 * kernels.rigidity_matrix_numpy(x, c.edges())[:, free], f)
    assert np.max(np.abs(kernels.residual_numpy(x, c.edges()))) < 1e-13
    return x


@SETTINGS
@given(st.sampled_from(["glued8", "glued9", "glued10", "polytetrahedron", "octahedron"]), seeds, st.booleans())
def test_exact_cluster_is_proved_within_round_off_whatever_the_frame_labels_and_mirror(name, seed, reflect) -> None:
    c = CLUSTERS[name]
    base = exact_cluster(c)
    moved = exact_cluster(transformed(c, seed, reflect))
    for e in (base, moved):
        assert e.status == PROVED and e.proved
        assert 0 < e.radius < 1e-12 and e.h < 1e-10 and e.unique > 1e-3
        assert abs(e.gap - c.min_gap()) < 1e-12


def test_the_root_is_within_the_radius_and_its_gaps_above_the_bound_for_every_perturbation() -> None:
    """A regular n = 7 cluster moved off its root by growing random displacements: the theorem's radius
    holds the root Newton's method finds, the exact gap bound is below the root's gap, and when the
    displacement is too large the theorem declines (too-far) or the gap is not proved (gap)."""
    c = min(regular(7), key=lambda c: c.min_gap())  # a gap of 0.051: the bound on it can fail first
    rng = np.random.default_rng(1)
    d = rng.normal(size=c.coords.shape)
    seen = set()
    for eps in np.geomspace(1e-9, 0.3, 80):
        moved = Cluster(c.coords + eps * d / np.linalg.norm(d), c.contacts)
        e = exact_cluster(moved)
        seen.add(e.status)
        if e.status in (PROVED, GAP):
            x0 = kernels.to_frame(moved.coords, contact_triangle(moved.edges())).ravel()
            root = newton_root(moved)
            assert np.linalg.norm(root - x0) <= e.radius * (1 + 1e-9) + 1e-15
            assert Cluster(root.reshape(-1, 3), c.contacts).min_gap() >= e.gap - 1e-12
            assert (e.status == PROVED) == (e.gap > 0)
        else:
            assert e.status == TOO_FAR and e.h > 0.5 and e.radius is None
    assert seen == {PROVED, GAP, TOO_FAR}


def test_a_cluster_whose_spheres_all_touch_is_proved_with_no_gap() -> None:
    """The tetrahedron: no non-contact pair, so no gap (None, as the min_gap column has it), and proved."""
    e = exact_cluster(CLUSTERS["tetrahedron"])
    assert e.proved and e.gap is None and e.radius < 1e-12 and e.others == 0.0


def test_singular_clusters_and_too_few_contacts_are_not_tried() -> None:
    nine = list(catalogue(9).clusters)
    assert [exact_cluster(c).status for c in nine].count(SINGULAR) == 1  # the n = 9 cluster with a flex
    data = json.loads((DATA / "clusters_n10.json").read_text())
    assert exact_cluster(Cluster.from_dict(data["n10_m23_prestress"])).status == NOT_RIGID  # 23 < 3n - 6
    assert exact_cluster(Cluster.from_dict(data["n10_m24_prestress"])).status == SINGULAR


def test_a_hyperstatic_cluster_proves_a_root_of_independent_contacts_and_bounds_the_others() -> None:
    """n = 10 with 25 contacts: 24 independent equations have a root within round-off, at which the 25th
    contact's |distance^2 - 1| is bounded by round-off too; relabelled, rotated and mirrored, the same."""
    data = json.loads((DATA / "clusters_n10.json").read_text())
    c = Cluster.from_dict(data["n10_m25_first-order"])
    for k, d in enumerate([c] + [transformed(c, seed, seed % 2 == 1) for seed in range(4)]):
        e = exact_cluster(d)
        assert e.proved and e.radius < 1e-12 and 0 < e.others < 1e-11, k
        assert abs(e.gap - c.min_gap()) < 1e-11


def test_two_geometries_of_one_graph_are_told_apart_and_copies_are_not() -> None:
    a, b = two_geometries()
    ea, eb = exact_cluster(a), exact_cluster(b)
    assert ea.proved and eb.proved
    assert not_told_apart([a, b], [ea, eb]) == []
    # a rotated, mirrored, relabelled copy of a: the same exact cluster
    copy = transformed(a, 7, True)
    [(i, j, bound)] = not_told_apart([a, b, copy], [ea, eb, exact_cluster(copy)])
    assert (i, j) == (0, 2) and bound < 1e-12
    # a copy with one sphere moved by 5e-5: its exact cluster is a's (within its radius), so not told apart
    x = a.coords.copy()
    x[3] += 5e-5
    near = Cluster(x, a.contacts)
    en = exact_cluster(near)
    assert en.proved and en.radius > 1e-5
    [(i, j, bound)] = not_told_apart([a, near], [ea, en])
    assert bound <= ea.radius + en.radius
    # a lower bound: below the distance with no alignment at all, one sphere moved by 5e-5 sqrt(3)
    assert 0 < distance_lower_bound(_canonical(a), _canonical(near)) <= 5e-5 * np.sqrt(3)
    # a cluster with no root proved is left out of the comparison
    far = Cluster(a.coords + 0.2 * np.random.default_rng(0).normal(size=a.coords.shape), a.contacts)
    assert exact_cluster(far).status == TOO_FAR
    assert not_told_apart([a, far], [ea, exact_cluster(far)]) == []
    with pytest.raises(ValueError, match="one contact graph"):
        not_told_apart([a, CLUSTERS["glued10"]], [ea, exact_cluster(CLUSTERS["glued10"])])


# --------------------------------------------------------------------------- the endpoint rule


def unproved_point() -> tuple[Cluster, Cluster]:
    """tests/data/n13_unproved.json: a point an n = 13 run stored as a first-order rigid cluster of 33
    contacts, and the 35-contact cluster that is the only root of its contact equations nearby."""
    data = json.loads((DATA / "n13_unproved.json").read_text())
    return Cluster.from_dict(data["unproved"]), Cluster.from_dict(data["root"])


def pinnings(c: Cluster):
    """Every ordered triangle of contacts of ``c``, with the point in its frame and the free coordinates."""
    adj = c.adjacency()
    for a in range(c.n):
        for b in range(c.n):
            for d in range(c.n):
                if a != b != d != a and adj[a, b] and adj[b, d] and adj[a, d]:
                    tri = (a, b, d)
                    yield tri, kernels.to_frame(c.coords, tri).ravel(), kernels.free_coordinates(c.n, tri)


def test_a_point_that_only_satisfies_newtons_tolerance_is_no_cluster() -> None:
    """The n = 13 point: its residual (2.7e-8) is below Newton's tolerance (3e-8), and with some pinned
    triangles its smallest singular value is above tol_n, so the rigidity test called it first-order rigid
    in those frames and a flex in the others.  No root is proved near it in any frame, and the endpoint
    rule says unproved in every frame where the old test said first-order (in the others the pre-stress
    test's accuracy check already declined it); the only root nearby is the 35-contact cluster 0.017 away
    (reached by Newton's method in 80-digit arithmetic from the point)."""
    from packings.workers.paths import UNPROVED_METHOD, endpoint_rigidity
    from packings.workers.rigidity import FIRST_ORDER, rigidity_without_stress

    point, root = unproved_point()
    f = kernels.residual_numpy(point.coords.ravel(), point.edges())
    assert 2e-8 < np.abs(f).max() < np.sqrt(DEFAULT.tol)
    first_order = 0
    for tri, x, free in pinnings(point):
        smin = np.linalg.svd(kernels.rigidity_matrix_numpy(x, point.edges())[:, free], compute_uv=False)[-1]
        first_order += smin > DEFAULT.tol_n
        assert not kantorovich(x, point.edges(), free).exists
        rig = endpoint_rigidity(x, point.contacts, free, DEFAULT)
        assert not rig.rigid, tri  # in the frames with a flex, the pre-stress test's accuracy check says so
        assert (rig.method == UNPROVED_METHOD) == (smin > DEFAULT.tol_n), tri
    assert first_order > 0 and rigidity_without_stress(0).kind == FIRST_ORDER
    assert exact_cluster(root).proved and root.m == 35 and set(point.contacts) < set(root.contacts)
    from packings.workers.identity import geometry_distance

    # 3.7e-3 the largest coordinate after alignment (0.017 over all coordinates), and its closest
    # non-contact pair 5.7e-3 from touching: both beyond tol_a0, so the near-pair rule did not see it
    assert 3e-3 < geometry_distance(Cluster(point.coords, root.contacts), root) < 5e-3
    assert point.min_gap() > DEFAULT.tol_a0


def test_the_endpoint_rule_keeps_every_first_order_cluster_of_n_9() -> None:
    """Every first-order cluster of an enumeration, in every pinned frame: the rule's proof holds with h
    far below 1/2, so the rule changes nothing where the clusters are what they seem."""
    from packings.workers.paths import endpoint_rigidity

    for c in catalogue(9).clusters:
        for k, (tri, x, free) in enumerate(pinnings(c)):
            if k % 7:
                continue
            rig = endpoint_rigidity(x, c.contacts, free, DEFAULT)
            if rig.flexes == 0:
                e = kantorovich(x, c.edges(), free)
                assert rig.rigid and e.proved and e.h < 1e-6


def test_root_exists_agrees_with_the_theorem_with_or_without_a_bound_on_sigma() -> None:
    """The endpoint rule's cheap route (a lower bound of σ_min from the rigidity test, then only the
    residuals) says what the whole theorem says: yes for every regular n = 9 cluster, no for the n = 13
    point, whose residual no bound on σ_min can make small enough."""
    import math

    from packings.workers.exact import root_exists

    certified = math.sqrt(kernels.guard_threshold(DEFAULT.tol_n))
    for c in catalogue(9).clusters:
        tri = contact_triangle(c.edges())
        x, free = kernels.to_frame(c.coords, tri).ravel(), kernels.free_coordinates(c.n, tri)
        whole = kantorovich(x, c.edges(), free).exists
        assert root_exists(x, c.edges(), free, DEFAULT.tol_n, certified) is (
            whole or c.m != 3 * c.n - 6 or exact_cluster(c).status == SINGULAR
        )
        assert root_exists(x, c.edges(), free, DEFAULT.tol_n) is whole
    point, _ = unproved_point()
    for tri, x, free in list(pinnings(point))[:10]:
        assert not root_exists(x, point.edges(), free, DEFAULT.tol_n, certified)
