"""packings.workers.catalysis: the rigid remainders of a cluster after deleting spheres."""

import json
from collections import Counter
from math import comb
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packings.workers.catalysis import (
    CONTACTS_DIFFER,
    FEW_CONTACTS,
    NOT_RIGID,
    Moved,
    Seen,
    _floppy,
    _measured_last,
    _without,
    first_triangles_without,
    glued,
    moved_remainders,
    remainder,
    remainder_count,
    remainders,
    rigid_remainders,
    sub_cluster,
)
from packings.workers.cluster import Cluster, contacts_from_coords, pair_distances
from packings.workers.identity import adjacency_certificate, certificate_key, edges_certificate, graph_certificate
from packings.workers.outcomes import BELOW_MIN_CONTACTS, RIGID
from packings.workers.params import Params
from packings.workers.rigidity import contact_triangle, rigidity, rigidity_without_stress
from packings.workers.seeds import seed_cluster
from tests.helpers import congruent_copy

P = Params()
DATA = Path(__file__).parent.parent / "data"
N10 = {k: Cluster.from_dict(v) for k, v in json.loads((DATA / "clusters_n10.json").read_text()).items()}


def octahedron() -> Cluster:
    s = 1 / np.sqrt(2.0)
    x = np.array([[s, 0, 0], [-s, 0, 0], [0, s, 0], [0, -s, 0], [0, 0, s], [0, 0, -s]])
    return Cluster.from_coords(x)


def test_deleting_a_sphere_of_the_octahedron_leaves_a_square_pyramid_which_is_not_rigid():
    out = list(remainders(octahedron(), 1, P))
    assert len(out) == 6
    for r in out:
        assert r.cluster.n == 5 and r.cluster.m == 8  # the square pyramid: 3n - 6 = 9 would be needed
        assert r.outcome == NOT_RIGID and r.rigidity.flexes == 1 and not r.rigidity.rigid
    assert rigid_remainders(octahedron(), 1, P) == []


def test_deleting_a_sphere_of_three_contacts_from_the_6_polytetrahedron_leaves_the_bipyramid():
    """The polytetrahedron of 6 (three tetrahedra face to face) has two spheres of three contacts; deleting
    either leaves the triangular bipyramid (the one rigid cluster of 5); deleting any other sphere leaves a
    sphere with fewer than three contacts."""
    parent = seed_cluster(6)
    degree = np.bincount(parent.edges().ravel())
    ends = [i for i in range(6) if degree[i] == 3]
    assert len(ends) == 2
    rigid = rigid_remainders(parent, 1, P)
    assert [r.deleted for r in rigid] == [(i,) for i in ends]
    bipyramid = certificate_key(seed_cluster(5))
    for r in rigid:
        assert r.cluster.m == 9 and certificate_key(r.cluster) == bipyramid
        assert r.rigidity.rigid and r.rigidity.flexes == 0
    assert {r.outcome for r in remainders(parent, 1, P) if not r.rigid} == {FEW_CONTACTS}


def test_remainder_is_the_parents_spheres_and_contacts_renumbered():
    parent = N10["n10_m25_first-order"]
    r = remainder(parent, (7, 2), P)
    assert r.deleted == (2, 7) and r.kept == tuple(i for i in range(10) if i not in (2, 7))
    assert np.array_equal(r.cluster.coords, parent.coords[list(r.kept)])
    back = {(r.kept[i], r.kept[j]) for i, j in r.cluster.contacts}
    assert back == {(i, j) for i, j in parent.contacts if i not in (2, 7) and j not in (2, 7)}
    assert all(i < j for i, j in r.cluster.contacts) and list(r.cluster.contacts) == sorted(r.cluster.contacts)


def test_every_deleted_set_is_tried_once():
    parent = N10["n10_m24_first-order"]
    for k in (1, 2, 3):
        out = list(remainders(parent, k, P))
        assert len(out) == comb(10, k) == remainder_count(10, k)
        assert len({r.deleted for r in out}) == len(out)
    with pytest.raises(ValueError):
        list(remainders(parent, 0, P))
    with pytest.raises(ValueError):
        list(remainders(parent, 8, P))


@pytest.mark.parametrize("name", sorted(N10))
def test_the_verdicts_are_the_rigidity_tests(name):
    """Rigid remainders are what packings.workers.rigidity.rigidity calls rigid, and so are no others: the shortcut
    for a sphere of fewer than three contacts and the SVD-free certificate change nothing."""
    for k in (1, 2):
        for r in remainders(N10[name], k, P):
            if r.outcome in (RIGID, NOT_RIGID, FEW_CONTACTS):
                full = rigidity(r.cluster.coords, r.cluster.contacts, P)
                assert full.rigid == r.rigid, (name, r.deleted, r.outcome)
                if r.rigidity is not None:
                    assert (full.kind, full.flexes) == (r.rigidity.kind, r.rigidity.flexes)


def test_rigid_remainders_of_clusters_of_10_are_rigid_clusters_of_9_with_their_measured_contacts():
    found = 0
    for parent in N10.values():
        for r in rigid_remainders(parent, 1, P):
            found += 1
            assert r.cluster.n == 9 and r.rigidity.rigid
            assert contacts_from_coords(r.cluster.coords, P.tol_a) == r.cluster.contacts
            assert r.cluster.m >= 3 * 9 - 8  # hypostatic at most by two at n = 9 (the paper: all 3n - 6)
    assert found > 0


def test_min_contacts_is_the_endpoint_rule():
    parent = N10["n10_m25_first-order"]
    rigid = rigid_remainders(parent, 1, P)
    most = max(r.cluster.m for r in rigid)
    strict = P.with_(min_contacts=most)
    kept = rigid_remainders(parent, 1, strict)
    assert [r.deleted for r in kept] == [r.deleted for r in rigid if r.cluster.m >= most]
    below = [r for r in remainders(parent, 1, strict) if r.outcome == BELOW_MIN_CONTACTS]
    assert [r.deleted for r in below] == [r.deleted for r in rigid if r.cluster.m < most]


def test_a_remainder_whose_geometry_has_other_contacts_is_rejected():
    """A parent whose contact list leaves out a touching pair (never a stored cluster) gives remainders
    with that pair whose measured contacts differ; they are rejected, not kept with the wrong contacts."""
    parent = N10["n10_m25_first-order"]
    left_out = parent.contacts[-1]
    bad = Cluster(parent.coords, parent.contacts[:-1])
    out = {r.deleted: r for r in remainders(bad, 1, P)}
    for (d,), r in out.items():
        if d not in left_out and r.outcome != FEW_CONTACTS:
            assert r.outcome == CONTACTS_DIFFER
    assert any(r.outcome == CONTACTS_DIFFER for r in out.values())


def _certificates(parent: Cluster, k: int) -> Counter:
    return Counter(certificate_key(r.cluster) for r in rigid_remainders(parent, k, P))


@settings(max_examples=8, deadline=None, derandomize=True)
@given(st.sampled_from(sorted(N10)), st.integers(0, 2**31 - 1), st.booleans())
def test_relabelling_rotating_and_reflecting_the_parent_changes_nothing(name, seed, reflect):
    """The same deleted sets (relabelled) are rigid, with the same certificates."""
    parent = N10[name]
    other, inv = congruent_copy(parent, seed, reflect)
    a = {r.deleted: certificate_key(r.cluster) for r in rigid_remainders(parent, 1, P)}
    b = {r.deleted: certificate_key(r.cluster) for r in rigid_remainders(other, 1, P)}
    assert b == {(int(inv[d]),): cert for (d,), cert in a.items()}
    assert _certificates(parent, 2) == _certificates(other, 2)


def test_sub_cluster_keeps_the_given_order():
    parent = N10["n10_m24_first-order"]
    c = sub_cluster(parent, (3, 0, 1))
    assert np.array_equal(c.coords, parent.coords[[3, 0, 1]])
    assert set(c.contacts) == {
        (min(a, b), max(a, b))
        for a, b in [
            ({3: 0, 0: 1, 1: 2}[i], {3: 0, 0: 1, 1: 2}[j])
            for i, j in parent.contacts
            if i in (3, 0, 1) and j in (3, 0, 1)
        ]
    }


def test_the_lost_cluster_of_11_is_a_remainder_of_its_parent_of_12_and_no_path_leaves_it():
    """tests/data/n11_catalysis.json: the cluster of 12 whose remainder without sphere 9 is the cluster of 11
    that the path enumeration does not reach (docs/method.md).  The remainder is rigid (pre-
    stress stable: two flexes, one stress) with 26 contacts (3n - 7), an hcp fragment; and, as the paper
    describes it, breaking either of two of its contacts, or both, leaves it rigid (dimension 0) and
    breaking any other contact leaves two degrees of freedom, any other pair three: no subset leaves a
    one-dimensional set, so no path leaves it, and none can arrive (a path's reverse would leave it)."""
    from packings.workers.classify import lattice_type
    from packings.workers.expand import expand
    from packings.workers.outcomes import NOT_1D

    data = json.loads((DATA / "n11_catalysis.json").read_text())
    parent = Cluster(np.array(data["parent"]["coords"]), tuple(map(tuple, data["parent"]["contacts"])))
    assert certificate_key(parent) == data["parent"]["certificate"]
    r = remainder(parent, data["deleted"], P)
    c = r.cluster
    assert r.rigid and (c.n, c.m) == (11, 26)
    assert (r.rigidity.kind, r.rigidity.flexes, r.rigidity.stresses) == ("prestress", 2, 1)
    assert certificate_key(c) == data["certificate"]
    assert lattice_type(c.coords, c.contacts) == "hcp"
    ex = expand(c, P)
    assert ex.paths_followed == 0 and set(ex.outcomes()) == {NOT_1D}
    single = {e.broken[0]: e.dim for e in ex.endpoints if len(e.broken) == 1}
    assert len(single) == 26 and Counter(single.values()) == {2: 24, 0: 2}
    pairs = {e.broken: e.dim for e in ex.endpoints if len(e.broken) == 2}
    rigid_two = tuple(sorted(b for b, d in single.items() if d == 0))
    assert len(pairs) == comb(26, 2) and pairs.pop(rigid_two) == 0
    assert set(pairs.values()) == {3}


# --------------------------------------------------------------------------- one sphere moved (--glued)


def _glued_n11() -> tuple[Cluster, dict]:
    data = json.loads((DATA / "n11_glued.json").read_text())
    c = data["cluster"]
    return Cluster(np.array(c["coords"]), tuple(map(tuple, c["contacts"]))), data


@pytest.mark.parametrize("name", sorted(N10))
def test_a_glued_sphere_touches_its_triangle_overlaps_nothing_and_has_its_measured_contacts(name):
    c = N10[name]
    out = list(glued(c, P))
    triangles_ = {tri for tri, _ in out}
    assert triangles_ and all(len(tri) == 3 for tri in triangles_)
    for tri, parent in out:
        assert parent.n == c.n + 1 and np.array_equal(parent.coords[:-1], c.coords)
        d = np.linalg.norm(c.coords - parent.coords[-1], axis=1)
        assert np.allclose(d[list(tri)], 1.0, atol=1e-12)
        assert d.min() >= 1.0 - P.tol_a
        assert parent.contacts == contacts_from_coords(parent.coords, P.tol_a)
    assert len(out) <= 2 * len(triangles_)


def test_one_side_of_every_face_of_a_tetrahedron():
    """One side of each face is the fourth sphere's own place (an overlap); the other is free, 2 sqrt(2/3)
    from the fourth sphere: four glued clusters of 5 with 9 contacts, the triangular bipyramid."""
    tet = seed_cluster(4)
    out = list(glued(tet, P))
    assert [tri for tri, _ in out] == [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)]
    assert all(p.m == 9 for _, p in out)
    assert len({certificate_key(p) for _, p in out}) == 1


def _moved_onto(c: Cluster, data: dict, certificate: str):
    """The one rigid remainder of moving a sphere of ``c`` that has ``certificate``, checked to be data's
    sphere moved onto data's triangle; and every rigid remainder."""
    seen = Seen(P.tol_d)
    assert seen.add(c)
    rigid = [mv for mv in moved_remainders(c, P, seen) if mv.remainder is not None and mv.remainder.rigid]
    [mv] = [mv for mv in rigid if certificate_key(mv.remainder.cluster) == certificate]
    assert (mv.sphere, mv.triangle) == (data["sphere"], tuple(data["triangle"]))
    return mv, rigid


def test_moving_a_sphere_finds_the_cluster_of_11_no_path_reaches():
    """tests/data/n11_glued.json: a path cluster of 11 whose sphere 0, moved onto the contact triangle
    (1, 5, 8), gives the rigid hcp fragment of 26 contacts that no path reaches (the one
    n11_catalysis.json gets from a cluster of 12); nothing else new and rigid is found from it."""
    from packings.workers.classify import lattice_type

    c, data = _glued_n11()
    mv, rigid = _moved_onto(c, data, data["certificate"])
    r = mv.remainder
    assert (r.cluster.n, r.cluster.m, r.rigidity.kind) == (11, 26, "prestress")
    assert lattice_type(r.cluster.coords, r.cluster.contacts) == "hcp"
    # the remainder's spheres: the cluster's without the moved one, in order, then the moved one
    assert np.array_equal(r.cluster.coords[:-1], np.delete(c.coords, mv.sphere, axis=0))
    assert sum(1 for mv in rigid if certificate_key(mv.remainder.cluster) == certificate_key(c)) == 0


def test_moving_a_sphere_finds_the_cluster_of_13_no_path_reaches():
    """tests/data/n13_glued.json: a path cluster of 13 whose sphere 7, moved onto the contact triangle
    (0, 3, 6), gives a rigid cluster with 32 contacts (two flexes held by one self-stress) that the path
    enumeration of 13 lacks: the one that makes its 1,220 the paper's 1,221.  No path from it ends at a
    rigid cluster, so none from a rigid cluster ends at it."""
    from packings.workers.expand import expand
    from packings.workers.identity import same_geometry

    data = json.loads((DATA / "n13_glued.json").read_text())
    c = Cluster(np.array(data["cluster"]["coords"]), tuple(map(tuple, data["cluster"]["contacts"])))
    found = data["found"]
    r = _moved_onto(c, data, found["certificate"])[0].remainder
    assert (r.cluster.n, r.cluster.m, r.rigidity.kind, r.rigidity.flexes) == (13, 32, "prestress", 2)
    assert r.rigidity.margin > 1000 * P.tol_psd
    assert same_geometry(r.cluster, Cluster(np.array(found["coords"]), tuple(map(tuple, found["contacts"]))), P.tol_d)
    out = expand(r.cluster, P)
    assert out.paths_followed > 0 and out.rigid_endpoints() == []


def test_a_remainder_seen_is_not_decided_again():
    """A second pass over the same record decides nothing again: each remainder is seen, or certified floppy
    from its glued cluster as before (those are never looked up)."""
    c, _ = _glued_n11()
    seen = Seen(P.tol_d)
    first = list(moved_remainders(c, P, seen))
    decided = sum(mv.remainder is not None for mv in first)
    assert decided > 0 and len(seen) >= decided and any(mv.floppy for mv in first)
    again = list(moved_remainders(c, P, seen))
    assert [(mv.sphere, mv.triangle, mv.side) for mv in again] == [(mv.sphere, mv.triangle, mv.side) for mv in first]
    assert all(mv.remainder is None for mv in again)
    assert [mv.floppy for mv in again] == [mv.floppy for mv in first]


@settings(max_examples=10, deadline=None, derandomize=True)
@given(st.sampled_from(sorted(N10)), st.integers(0, 2**31 - 1), st.booleans())
def test_a_cluster_relabelled_rotated_and_reflected_is_seen(name, seed, reflect):
    seen = Seen(P.tol_d)
    assert seen.add(N10[name])
    assert not seen.add(congruent_copy(N10[name], seed, reflect)[0])
    assert all(seen.add(N10[other]) for other in sorted(N10) if other != name)


def _plain_record(bound: float):
    """The record Seen keeps, kept plainly: every graph's float64 distances in a list, compared one by one."""
    by_graph: dict[bytes, list[np.ndarray]] = {}

    def add(graph: bytes, d: np.ndarray) -> bool:
        others = by_graph.setdefault(graph, [])
        if any(np.max(np.abs(d - o)) <= bound for o in others):
            return False
        others.append(d)
        return True

    return add


@settings(max_examples=6, deadline=None, derandomize=True)
@given(st.integers(0, 2**31 - 1))
def test_the_record_calls_seen_only_what_a_plain_one_calls_seen(seed):
    """Seen's record (128-bit digests of the graph and the distances rounded to cells of 4 tol_d, in a table
    that grows) on a stream of 45,000 clusters of 1,500 graphs, each three geometries, each given again
    shifted by 0 up to 1e-3 or jittered by 1e-9: its answer is always that of a plain record of the cells,
    it never calls seen a cluster that the plain record of distances within 4 tol_d calls new, and an exact
    copy of a cluster given before is always seen."""
    rng = np.random.default_rng(seed)
    bound = 4 * P.tol_d
    graphs = [rng.bytes(104) for _ in range(1_500)]
    shapes = {(g, k): np.sort(rng.uniform(1.0, 3.0, 78)) for g in range(len(graphs)) for k in range(3)}
    shifts = np.array([0.0, 1e-7, 1e-5, 2e-5, 1e-4, 1e-3, np.nan])  # nan: jittered by up to 1e-9
    seen, plain, cells = Seen(P.tol_d), _plain_record(bound), set()
    answers, given_exactly, exact_again = [], set(), 0
    for _ in range(45_000):
        g, k, shift = int(rng.integers(len(graphs))), int(rng.integers(3)), shifts[rng.integers(shifts.size)]
        d = shapes[g, k] + (rng.uniform(-1e-9, 1e-9, 78) if np.isnan(shift) else shift)
        key = (graphs[g], tuple(np.rint(d / bound).astype(int)))
        known = key in cells
        cells.add(key)
        new_plain = plain(graphs[g], d)
        answers.append(seen.add_parts(graphs[g], d))
        assert answers[-1] == (not known)
        assert new_plain <= answers[-1]  # new by distances: new here too
        if shift == 0.0:
            if (g, k) in given_exactly:  # an exact copy of a cluster given before: seen
                assert not answers[-1]
                exact_again += 1
            given_exactly.add((g, k))
    assert len(seen) == sum(answers) == len(cells) and 0 < sum(answers) < len(answers)
    assert exact_again > 1_000
    assert len(seen._keys) > 2 * len(graphs) > 1 << 10  # grown from its first size


@settings(max_examples=5, deadline=None, derandomize=True)
@given(st.integers(0, 2**31 - 1), st.integers(0, 12))
def test_the_table_keeps_every_digest_through_its_growth(seed, shared_bits):
    """Digests whose home slots crowd together (the low ``shared_bits`` bits the same, so that probing runs
    long) added to the table as it doubles: each is found again, and only those; the table is at most half
    full, and holds each digest in one slot, reachable from its home slot through occupied slots.  The
    digests are placed a chunk at a time as the table grows: chunks of 257 here, so that each growth takes
    several."""
    from unittest import mock

    from packings.workers import catalysis

    rng = np.random.default_rng(seed)
    lo = rng.integers(1, 2**63, 6_000, dtype=np.uint64) & ~np.uint64((1 << shared_bits) - 1)
    hi = rng.integers(0, 2**63, 6_000, dtype=np.uint64)
    seen = Seen(P.tol_d)
    with mock.patch.object(catalysis, "GROW_CHUNK", 257):
        assert all(seen._add(int(a), int(b)) for a, b in zip(lo[:5_000], hi[:5_000]))
    assert not any(seen._add(int(a), int(b)) for a, b in zip(lo[:5_000], hi[:5_000]))
    assert all(seen._add(int(a), int(b)) for a, b in zip(lo[5_000:], hi[5_000:]))  # new: added
    table = seen._keys
    occupied = (table[:, 0] != 0) | (table[:, 1] != 0)
    assert len(seen) == 6_000 == occupied.sum() and len(table) >= 2 * len(seen) and len(table) > 1 << 10
    stored = {(int(a), int(b)) for a, b in table[occupied]}
    assert stored == {(int(a), int(b)) for a, b in zip(lo, hi)}
    mask = len(table) - 1
    for i in np.flatnonzero(occupied)[::7]:  # probing from the home slot meets no empty slot before i
        home = int(table[i, 0]) & mask
        assert occupied[np.arange(home, home + ((i - home) & mask) + 1) & mask].all()


def test_copies_within_a_millionth_of_the_cell_are_seen():
    """Copies of a shape whose distances differ by up to 1e-9 (repeats of one remainder agree that closely,
    docs/method.md) are called seen unless a distance lies within 1e-9 of a cell's wall."""
    rng = np.random.default_rng(7)
    seen, bound = Seen(P.tol_d), 4 * P.tol_d
    d = np.sort(rng.uniform(1.0, 3.0, 78))
    d = d[np.abs(d / bound - np.floor(d / bound) - 0.5) > 1e-3]  # rint's walls: halfway between multiples
    assert seen.add_parts(b"graph", d)
    assert not any(seen.add_parts(b"graph", d + rng.uniform(-1e-9, 1e-9, d.size)) for _ in range(200))
    assert seen.add_parts(b"another graph", d) and len(seen) == 2


def test_two_geometries_of_one_graph_are_both_new():
    data = json.loads((DATA / "n11_two_geometries.json").read_text())
    a, b = (Cluster.from_dict(c) for c in data["clusters"][:2])
    assert certificate_key(a) == certificate_key(b)
    seen = Seen(P.tol_d)
    assert seen.add(a) and seen.add(b) and len(seen) == 2


@settings(max_examples=4, deadline=None, derandomize=True)
@given(st.integers(0, 2**31 - 1), st.booleans())
def test_moving_spheres_of_a_relabelled_rotated_reflected_cluster_finds_the_same(seed, reflect):
    c, _ = _glued_n11()
    other, _ = congruent_copy(c, seed, reflect)

    def found(x):
        return Counter(
            certificate_key(mv.remainder.cluster)
            for mv in moved_remainders(x, P, Seen(P.tol_d))
            if mv.remainder is not None and mv.remainder.rigid
        )

    assert found(c) == found(other)


def _movable(cluster: Cluster):
    """(sphere, triangle, side, glued cluster) of every sphere of ``cluster`` moved onto a contact triangle
    whose removal leaves every sphere three contacts, in moved_remainders' order, worked out from nothing
    moved_remainders computes."""
    sides = {}
    for tri, parent in glued(cluster, P):
        side = sides[tri] = sides.get(tri, -1) + 1
        degree = np.bincount(parent.edges().ravel(), minlength=parent.n)
        for s in range(cluster.n):
            left = degree.copy()
            left[[j for i, j in parent.contacts if i == s] + [i for i, j in parent.contacts if j == s]] -= 1
            left[s] = 3
            if left.min() >= 3:
                yield s, tri, side, parent


def _moved_one_by_one(cluster: Cluster, seen: Seen) -> list[Moved]:
    """moved_remainders as it was before the floppy remainders were certified together: each glued cluster's
    spheres in turn, the remainder built and decided by :func:`remainder` from nothing it inherits."""
    out = []
    for s, tri, side, parent in _movable(cluster):
        rest = [i for i in range(parent.n) if i != s]
        if not seen.add_parts(
            graph_certificate(sub_cluster(parent, rest)),
            np.sort(pair_distances(parent.coords)[_without(parent.n, s)]),
        ):
            out.append(Moved(s, tri, side, None))
            continue
        out.append(Moved(s, tri, side, remainder(parent, (s,), P)))
    return out


def _decided_alone(cluster: Cluster) -> list[tuple]:
    """Every remainder moving a sphere of ``cluster`` gives where each sphere keeps three contacts, built and
    decided by :func:`remainder` from nothing it inherits and with no record of those seen: (sphere, triangle,
    side, glued cluster, remainder) each, in moved_remainders' order."""
    return [(s, tri, side, parent, remainder(parent, (s,), P)) for s, tri, side, parent in _movable(cluster)]


def _fields(r) -> tuple:
    """Every field of a remainder, the coordinates as bytes."""
    return (r.deleted, r.kept, r.outcome, r.rigidity, r.cluster.coords.tobytes(), r.cluster.contacts)


def _as_compared(moved: list[Moved]) -> list[tuple]:
    """Every field of each Moved and of its remainder, the coordinates as bytes."""
    out = []
    for mv in moved:
        r = mv.remainder
        out.append(
            (mv.sphere, mv.triangle, mv.side)
            + (
                ()
                if r is None
                else (r.deleted, r.kept, r.outcome, r.rigidity, r.cluster.coords.tobytes(), r.cluster.contacts)
            )
        )
    return out


def _clusters_to_move() -> dict[str, Cluster]:
    """The test clusters of 10, the path clusters of 11 and 13 whose moved spheres give clusters no path reaches
    (rigid remainders, singular ones), and two relabelled, rotated and reflected copies of the first."""
    out = dict(N10)
    out["n11_glued"] = _glued_n11()[0]
    data = json.loads((DATA / "n13_glued.json").read_text())
    out["n13_glued"] = Cluster(np.array(data["cluster"]["coords"]), tuple(map(tuple, data["cluster"]["contacts"])))
    for seed, reflect in ((1, False), (2, True)):
        out[f"n11_glued moved {seed}"] = congruent_copy(out["n11_glued"], seed, reflect)[0]
    return out


@pytest.mark.parametrize("name", sorted(_clusters_to_move()))
def test_moved_remainders_decides_as_each_remainder_decided_alone(name):
    """Moving each sphere (``moved_remainders``: floppy remainders certified together by the compiled kernels
    and not looked up in the record, the others given what their parent already settled) gives, field by field
    and the coordinates bit for bit, what building and deciding each remainder alone gives, for every remainder
    it certifies or decides; those it skips as seen repeat one decided before, and the rigid remainders are
    those of deciding every remainder alone."""
    c = _clusters_to_move()[name]
    alone = _decided_alone(c)
    got = list(moved_remainders(c, P, Seen(P.tol_d)))
    assert [(mv.sphere, mv.triangle, mv.side) for mv in got] == [(s, tri, side) for s, tri, side, _, _ in alone]
    decided = []
    for mv, (_, _, _, parent, r) in zip(got, alone):
        if mv.seen:
            assert certificate_key(r.cluster) in {certificate_key(x.cluster) for x in decided}
            continue
        decided.append(mv.built(parent))
        assert _fields(decided[-1]) == _fields(r)
        if mv.floppy:
            assert (r.outcome, r.rigidity.method, r.rigidity.flexes) == (NOT_RIGID, "no-stress", mv.floppy)
    assert any(mv.floppy for mv in got) and any(mv.remainder is not None for mv in got)
    assert {certificate_key(r.cluster) for r in decided if r.rigid} == {
        certificate_key(r.cluster) for *_, r in alone if r.rigid
    }


def test_a_cluster_whose_contacts_are_not_those_measured_is_decided_as_each_remainder_alone():
    """Where the contacts given are not those measured (a contact left out), no remainder takes the shortcut:
    each is decided as alone, ``contacts-differ``."""
    c = N10["n10_m24_first-order"]
    lost = Cluster(c.coords, c.contacts[1:])
    got, expected = list(moved_remainders(lost, P, Seen(P.tol_d))), _moved_one_by_one(lost, Seen(P.tol_d))
    assert _as_compared(got) == _as_compared(expected)
    outcomes = Counter(mv.remainder.outcome for mv in got if mv.remainder is not None)
    assert outcomes[CONTACTS_DIFFER] > 0 and outcomes[CONTACTS_DIFFER] == sum(outcomes.values())


def _glued_parts(c: Cluster):
    """The first glued cluster of ``c`` with its contacts, adjacency matrix and pair distances, as _floppy takes them."""
    tri, parent = next(iter(glued(c, P)))
    edges = parent.edges()
    adjacent = np.zeros((parent.n, parent.n), dtype=bool)
    adjacent[edges[:, 0], edges[:, 1]] = adjacent[edges[:, 1], edges[:, 0]] = True
    return parent, edges, adjacent, pair_distances(parent.coords)


def test_a_pair_near_touching_leaves_every_remainder_that_keeps_it_to_be_decided_alone():
    """A pair that is not a contact within tol_a0 (and NEAR_ROOM) of touching: no remainder that keeps both its
    spheres is certified floppy together (resolve_near_pairs may make it another cluster); the others are."""
    parent, edges, adjacent, d = _glued_parts(N10["n10_m24_first-order"])
    spheres = list(range(parent.n - 1))
    far = _floppy(parent, edges, adjacent, d, P, spheres)
    i = min(far)
    j = int(np.flatnonzero(~adjacent[i] & (np.arange(parent.n) != i))[0])
    d[i, j] = d[j, i] = 1.0 + P.tol_a0 / 2
    near = _floppy(parent, edges, adjacent, d, P, spheres)
    assert len(far) > 2 and i in near and set(near) == set(far) & {i, j}
    assert all(near[s] == far[s] for s in near)


def test_a_glued_sphere_whose_contacts_are_not_those_measured_leaves_its_remainders_to_be_decided_alone():
    parent, edges, adjacent, d = _glued_parts(N10["n10_m24_first-order"])
    assert _measured_last(parent, P.tol_a) and _floppy(parent, edges, adjacent, d, P, list(range(parent.n - 1)))
    last = parent.n - 1
    lost = Cluster(
        parent.coords, tuple(c for c in parent.contacts if c != [c for c in parent.contacts if last in c][0])
    )
    assert not _measured_last(lost, P.tol_a)
    assert _floppy(lost, lost.edges(), adjacent, d, P, list(range(parent.n - 1))) == {}


@settings(max_examples=20, deadline=None, derandomize=True)
@given(st.sampled_from(sorted(N10)), st.integers(0, 2**31 - 1), st.booleans())
def test_what_moving_a_sphere_takes_from_the_glued_cluster_is_what_each_remainder_has(name, seed, reflect):
    """For each glued cluster of a relabelled, rotated (reflected) test cluster of 10 and each remainder without
    one sphere: the parent's measured contacts are its own exactly where the cluster's and the glued sphere's
    are (_measured_last), and then the remainder's are too; its graph's certificate from the lists of larger
    neighbours is nauty's of its contacts; and the flexes _floppy certifies (of the remainders where every
    sphere keeps three contacts, as moved_remainders asks) are those the remainder, decided alone, finds floppy
    with."""
    c = congruent_copy(N10[name], seed, reflect)[0]
    cluster_measured = contacts_from_coords(c.coords, P.tol_a) == c.contacts
    for tri, parent in glued(c, P):
        edges = parent.edges()
        adjacent = np.zeros((parent.n, parent.n), dtype=bool)
        adjacent[edges[:, 0], edges[:, 1]] = adjacent[edges[:, 1], edges[:, 0]] = True
        measured = contacts_from_coords(parent.coords, P.tol_a) == parent.contacts
        assert (cluster_measured and _measured_last(parent, P.tol_a)) == measured
        rest = {s: sub_cluster(parent, [i for i in range(parent.n) if i != s]) for s in range(c.n)}
        enough = [s for s, r in rest.items() if np.bincount(r.edges().ravel(), minlength=r.n).min() >= 3]
        floppy = _floppy(parent, edges, adjacent, pair_distances(parent.coords), P, enough)
        assert set(floppy) <= set(enough)
        for s, r in rest.items():
            assert (contacts_from_coords(r.coords, P.tol_a) == r.contacts) == measured
            above = [[j for i2, j in r.contacts if i2 == i] for i in range(r.n)]
            assert adjacency_certificate(r.n, above) == edges_certificate(r.n, r.contacts)
            if s in floppy:
                alone = remainder(parent, (s,), P)
                assert (alone.outcome, alone.rigidity) == (NOT_RIGID, rigidity_without_stress(floppy[s]))


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.integers(3, 14), st.data())
def test_first_triangles_without_a_sphere_are_contact_triangles(n, data):
    """first_triangles_without is contact_triangle of the contacts without those of the sphere, for any graph."""
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    contacts = sorted(data.draw(st.lists(st.sampled_from(pairs), unique=True)))
    adjacent = np.zeros((n, n), dtype=bool)
    for i, j in contacts:
        adjacent[i, j] = adjacent[j, i] = True
    spheres = np.arange(n)
    got = first_triangles_without(adjacent, spheres)
    for s in range(n):
        expected = contact_triangle(contacts, forbidden=[c for c in contacts if s in c])
        assert (None if got[s, 0] < 0 else tuple(got[s].tolist())) == expected
