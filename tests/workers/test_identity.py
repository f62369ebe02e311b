"""Tests of packings.workers.identity: certificates, canonical labelling, automorphisms, geometry."""

from __future__ import annotations

import sys

import numpy as np
import pynauty
import pytest
from hypothesis import given
from hypothesis import strategies as st

from packings.workers import identity, kernels
from packings.workers.cluster import Cluster
from packings.workers.identity import (
    ClusterIndex,
    alignment,
    automorphisms,
    canonical_labelling,
    certificate,
    certificate_hex,
    embedding_position,
    find_match,
    same_geometry,
    symmetries,
)
from packings.workers.seeds import seed_cluster
from tests.helpers import (
    CHAIN_DIHEDRALS,
    CLUSTERS,
    SETTINGS,
    TOL_D,
    chain,
    names,
    random_glued,
    random_orthogonal,
    relabel,
    seeds,
    transformed,
)

# --------------------------------------------------------------------------- builders sanity


def test_test_clusters_are_what_they_claim() -> None:
    for name, c in CLUSTERS.items():
        assert c.min_distance() >= 1.0 - 1e-9, name
    assert (CLUSTERS["tetrahedron"].n, CLUSTERS["tetrahedron"].m) == (4, 6)
    assert (CLUSTERS["bipyramid"].n, CLUSTERS["bipyramid"].m) == (5, 9)
    assert (CLUSTERS["octahedron"].n, CLUSTERS["octahedron"].m) == (6, 12)
    assert (CLUSTERS["polytetrahedron"].n, CLUSTERS["polytetrahedron"].m) == (6, 12)
    for n in (8, 9, 10):
        c = CLUSTERS[f"glued{n}"]
        assert c.n == n and c.m >= 3 * n - 6


# --------------------------------------------------------------------------- certificates


@SETTINGS
@given(names, seeds, st.booleans())
def test_certificate_invariant_under_rigid_motion_and_relabelling(name, seed, reflect) -> None:
    c = CLUSTERS[name]
    t = transformed(c, seed, reflect)
    assert certificate(t) == certificate(c)
    assert certificate_hex(t) == certificate(c).hex()


def test_certificate_hex_is_plain_hex() -> None:
    h = certificate_hex(CLUSTERS["octahedron"])
    assert isinstance(h, str) and h == h.lower()
    assert bytes.fromhex(h) == certificate(CLUSTERS["octahedron"])


def test_octahedron_and_polytetrahedron_differ() -> None:
    assert certificate(CLUSTERS["octahedron"]) != certificate(CLUSTERS["polytetrahedron"])
    assert not same_geometry(CLUSTERS["octahedron"], CLUSTERS["polytetrahedron"], TOL_D)


def test_certificate_is_native_packed_canonical_adjacency() -> None:
    """Documents the certificate layout: n rows of native-endian setwords,
    bit j of row k (most significant first) = canonical adjacency [k, j]."""
    for c in CLUSTERS.values():
        cert = certificate(c)
        p = canonical_labelling(c)
        a = c.adjacency()[np.ix_(p, p)]
        row_bytes = len(cert) // c.n
        decoded = np.zeros_like(a)
        for k in range(c.n):
            bits = int.from_bytes(cert[k * row_bytes : (k + 1) * row_bytes], sys.byteorder)
            for j in range(c.n):
                decoded[k, j] = (bits >> (8 * row_bytes - 1 - j)) & 1
        assert np.array_equal(decoded, a)


# --------------------------------------------------------------------------- canonical labelling


@st.composite
def random_graphs(draw) -> Cluster:
    n = draw(st.integers(1, 12))
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    keep = draw(st.lists(st.booleans(), min_size=len(pairs), max_size=len(pairs)))
    return Cluster(np.zeros((n, 3)), tuple(p for p, k in zip(pairs, keep) if k))


@SETTINGS
@given(random_graphs(), seeds)
def test_canonical_labelling_gives_identical_adjacency(g, seed) -> None:
    h = relabel(g, np.random.default_rng(seed).permutation(g.n))
    pg, ph = canonical_labelling(g), canonical_labelling(h)
    assert sorted(pg.tolist()) == list(range(g.n))
    assert np.array_equal(g.adjacency()[np.ix_(pg, pg)], h.adjacency()[np.ix_(ph, ph)])
    assert certificate(g) == certificate(h)


@SETTINGS
@given(names, seeds, st.booleans())
def test_canonical_labelling_of_clusters(name, seed, reflect) -> None:
    c = CLUSTERS[name]
    t = transformed(c, seed, reflect)
    pc, pt = canonical_labelling(c), canonical_labelling(t)
    assert np.array_equal(c.adjacency()[np.ix_(pc, pc)], t.adjacency()[np.ix_(pt, pt)])


def test_canon_label_is_not_the_inverse_convention() -> None:
    """canon_label c means 'canonical k is original c[k]', not 'original i goes to c[i]'."""
    rng = np.random.default_rng(0)
    g = random_glued(10, 11)
    failures = 0
    for _ in range(20):
        h = relabel(g, rng.permutation(g.n))
        ig = np.argsort(np.asarray(pynauty.canon_label(_graph(g))))
        ih = np.argsort(np.asarray(pynauty.canon_label(_graph(h))))
        failures += not np.array_equal(g.adjacency()[np.ix_(ig, ig)], h.adjacency()[np.ix_(ih, ih)])
    assert failures > 0


def _graph(c: Cluster) -> pynauty.Graph:
    d = {i: [] for i in range(c.n)}
    for i, j in c.contacts:
        d[i].append(j)
    return pynauty.Graph(c.n, adjacency_dict=d)


# --------------------------------------------------------------------------- automorphisms


@pytest.mark.parametrize(
    "name,order",
    [("tetrahedron", 24), ("bipyramid", 12), ("octahedron", 48), ("chain60", 2), ("polytetrahedron", 4)],
)
def test_automorphism_group_orders(name, order) -> None:
    assert len(automorphisms(CLUSTERS[name])) == order


@pytest.mark.parametrize("name", sorted(CLUSTERS))
def test_automorphisms_form_the_group_of_the_canonical_graph(name) -> None:
    c = CLUSTERS[name]
    p = canonical_labelling(c)
    a = c.adjacency()[np.ix_(p, p)]
    group = automorphisms(c)
    assert np.array_equal(group[0], np.arange(c.n))
    keys = {s.tobytes() for s in group}
    assert len(keys) == len(group)
    for s in group:
        assert sorted(s.tolist()) == list(range(c.n))
        assert np.array_equal(a[np.ix_(s, s)], a)
    for s in group:
        for t in group:
            assert s[t].tobytes() in keys


# --------------------------------------------------------------------------- geometry


@SETTINGS
@given(names, seeds, st.booleans())
def test_same_geometry_under_rigid_motion_and_relabelling(name, seed, reflect) -> None:
    c = CLUSTERS[name]
    t = transformed(c, seed, reflect)
    assert same_geometry(c, t, TOL_D)
    assert same_geometry(t, c, TOL_D)


@SETTINGS
@given(names, seeds, st.booleans())
def test_the_alignment_relabels_a_cluster_onto_its_rotated_relabelled_copy(name, seed, reflect) -> None:
    """alignment(c, t)[i] is the sphere of t where sphere i of c is: c relabelled by it has t's contacts,
    and its coordinates are t's after an orthogonal alignment; a moved sphere gives None."""
    c = CLUSTERS[name]
    t = transformed(c, seed, reflect, noise=1e-7)
    a = alignment(c, t, TOL_D)
    assert a is not None and sorted(a.tolist()) == list(range(c.n))
    assert {tuple(sorted((int(a[i]), int(a[j])))) for i, j in c.contacts} == set(t.contacts)
    x, y = c.coords - c.coords.mean(axis=0), t.coords[a] - t.coords[a].mean(axis=0)
    assert kernels.aligned_max_error(x, y) <= TOL_D
    moved = t.coords.copy()
    moved[0] += 1e-3
    assert alignment(c, Cluster(moved, t.contacts), TOL_D) is None


@SETTINGS
@given(names, seeds, st.booleans())
def test_small_noise_keeps_same_geometry(name, seed, reflect) -> None:
    c = CLUSTERS[name]
    assert same_geometry(c, transformed(c, seed, reflect, noise=1e-7), TOL_D)


@SETTINGS
@given(names, seeds, st.booleans(), st.data())
def test_perturbing_one_sphere_breaks_same_geometry(name, seed, reflect, data) -> None:
    c = CLUSTERS[name]
    k = data.draw(st.integers(0, c.n - 1))
    rng = np.random.default_rng(seed)
    u = rng.normal(size=3)
    x = c.coords.copy()
    x[k] += 1e-3 * u / np.linalg.norm(u)
    moved = Cluster(x, c.contacts)  # same graph by construction
    assert certificate(moved) == certificate(c)
    assert not same_geometry(c, transformed(moved, seed, reflect), TOL_D)


def _both_backends(f):
    """f() under each kernel backend: {backend: value}."""
    out = {}
    for name in kernels.BACKENDS:
        with kernels.backend(name):
            out[name] = f()
    return out


@SETTINGS
@given(names, seeds, st.booleans(), st.floats(0.0, 4.0))
def test_compiled_and_numpy_comparisons_agree(name, seed, reflect, scale) -> None:
    """The comparison under every automorphism (kernels.some_automorphism_aligns) gives the same answer in
    both backends, for copies moved by up to a few tol_d (within, near and beyond the tolerance)."""
    c = CLUSTERS[name]
    moved = transformed(c, seed, reflect, noise=scale * TOL_D)
    answers = _both_backends(lambda: (same_geometry(c, moved, TOL_D), same_geometry(moved, c, TOL_D)))
    assert answers["numba"] == answers["numpy"]


@pytest.mark.parametrize("name", sorted(CLUSTERS))
def test_both_backends_accept_copies_and_reject_moved_spheres(name) -> None:
    c = CLUSTERS[name]
    x = c.coords.copy()
    x[0] += [3 * TOL_D, 0.0, 0.0]
    moved = Cluster(x, c.contacts)
    answers = _both_backends(
        lambda: (
            same_geometry(c, transformed(c, 1, True, noise=0.2 * TOL_D), TOL_D),
            same_geometry(c, transformed(moved, 2, False), TOL_D),
        )
    )
    assert answers == {"numba": (True, False), "numpy": (True, False)}


def test_same_graph_different_geometry() -> None:
    a, b = chain(60.0), chain(120.0)
    assert a.min_distance() >= 1.0 - 1e-9 and b.min_distance() >= 1.0 - 1e-9
    assert certificate(a) == certificate(b)
    assert not same_geometry(a, b, TOL_D)


def test_mirror_image_is_the_same_cluster() -> None:
    plus, minus = chain(60.0), chain(-60.0)
    assert same_geometry(plus, minus, TOL_D)
    # ... and only because reflections are allowed: no proper rotation matches.
    x = plus.coords - plus.coords.mean(axis=0)
    for perm in ([0, 1, 2, 3], [3, 2, 1, 0]):
        y = minus.coords[perm] - minus.coords.mean(axis=0)
        u, _, vt = np.linalg.svd(x.T @ y)
        d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
        assert np.max(np.abs(x @ (u @ d @ vt) - y)) > 1e-3


def test_different_sizes_are_different() -> None:
    assert not same_geometry(CLUSTERS["tetrahedron"], CLUSTERS["bipyramid"], TOL_D)


# --------------------------------------------------------------------------- find_match / index


def test_find_match() -> None:
    c = CLUSTERS["chain60"]
    candidates = [chain(120.0), chain(90.0), transformed(c, 7, True), c]
    assert find_match(c, candidates, TOL_D) == 2
    assert find_match(c, candidates[:2], TOL_D) is None
    assert find_match(c, [], TOL_D) is None
    assert find_match(c, iter(candidates), TOL_D) == 2


def test_cluster_index() -> None:
    idx = ClusterIndex()
    assert len(idx) == 0
    assert idx.add(chain(60.0), TOL_D) == (0, True)
    assert idx.add(chain(120.0), TOL_D) == (1, True)
    assert idx.add(chain(-60.0), TOL_D) == (0, False)  # mirror image
    assert idx.add(transformed(chain(120.0), 3, False, noise=1e-7), TOL_D) == (1, False)
    assert idx.embedding_number(0) == 0 and idx.embedding_number(1) == 1
    assert idx.add(CLUSTERS["octahedron"], TOL_D) == (2, True)
    assert idx.add(CLUSTERS["polytetrahedron"], TOL_D) == (3, True)
    assert idx.add(transformed(CLUSTERS["octahedron"], 9, True), TOL_D) == (2, False)
    assert idx.embedding_number(2) == 0 and idx.embedding_number(3) == 0
    assert len(idx) == 4
    assert idx[2] is CLUSTERS["octahedron"]
    assert [c.n for c in idx] == [4, 4, 6, 6]


@SETTINGS
@given(order=st.permutations(range(len(CHAIN_DIHEDRALS))), seed=st.integers(0, 10_000))
def test_embedding_numbers_follow_geometry_not_the_order_found(order, seed) -> None:
    """Geometries of one contact graph added in any order, each moved, reflected, relabelled and
    perturbed far below tol_d, get the same embedding numbers: the more compact one first."""
    idx = ClusterIndex()
    for i, k in enumerate(order):
        assert idx.add(transformed(chain(CHAIN_DIHEDRALS[k]), seed + i, bool((seed + i) % 2), noise=1e-7), TOL_D) == (
            i,
            True,
        )
    assert [idx.embedding_number(i) for i in range(len(order))] == list(order)
    for i, k in enumerate(order):  # a copy matches the geometry it copies, whatever its number
        assert idx.add(transformed(chain(-CHAIN_DIHEDRALS[k]), seed, True, noise=1e-7), TOL_D) == (i, False)


def test_embedding_position_orders_by_the_largest_distances_at_a_resolution_of_4_tol_d() -> None:
    geometries = [chain(d) for d in CHAIN_DIHEDRALS]
    assert [embedding_position(g, geometries, TOL_D) for g in geometries] == [1, 2, 3, 4, 5]  # after its equal
    assert embedding_position(chain(60.0), geometries, TOL_D) == 2
    assert embedding_position(chain(60.0), [], TOL_D) == 0
    # a copy within tol_d never goes before the geometry it copies; a change 10 tol_d along the 0-3
    # distance does
    near = chain(45.0)

    def stretched(by: float) -> Cluster:
        x = near.coords.copy()
        x[3] += by * TOL_D * (x[3] - x[0]) / np.linalg.norm(x[3] - x[0])
        return Cluster(x, near.contacts)

    assert embedding_position(stretched(1.5), geometries, TOL_D) == 2
    assert embedding_position(stretched(-1.5), geometries, TOL_D) == 2
    assert embedding_position(stretched(-10.0), geometries, TOL_D) == 1


def test_certificate_key_is_portable_and_equivalent_to_the_certificate():
    """The key is built from the canonical adjacency, so it agrees with certificate equality."""
    from packings.workers.identity import certificate_key

    rng = np.random.default_rng(7)
    base = seed_cluster(8)
    other = seed_cluster(9)
    p = rng.permutation(8)
    relabelled = Cluster(
        base.coords[p], tuple((int(np.argsort(p)[i]), int(np.argsort(p)[j])) for i, j in base.contacts)
    )
    assert certificate_key(relabelled) == certificate_key(base)
    assert certificate(relabelled) == certificate(base)
    assert certificate_key(base) != certificate_key(other)
    # 28 pairs for n = 8 -> 4 bytes; the bits are the contacts' count
    key = bytes.fromhex(certificate_key(base))
    assert len(key) == 4 and sum(bin(b).count("1") for b in key) == base.m


# --------------------------------------------------------------------------- the graph nauty is given


@SETTINGS
@given(st.integers(1, 16), st.data())
def test_the_contact_graph_gives_nauty_what_pynauty_s_own_graph_does(n, data) -> None:
    """_contact_graph skips pynauty.Graph's checks: the same labelling, certificate and automorphisms
    as pynauty's own graph of those edges, whatever their order (and a pynauty that stored its graph
    otherwise would fail here)."""
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    edges = data.draw(st.lists(st.sampled_from(pairs), unique=True) if pairs else st.just([]))
    ours = identity._contact_graph(n, edges)
    theirs = pynauty.Graph(n, adjacency_dict={i: [j for a, j in edges if a == i] for i in range(n)})
    assert isinstance(ours, pynauty.Graph)
    assert pynauty.canon_label(ours) == pynauty.canon_label(theirs)
    assert pynauty.certificate(ours) == pynauty.certificate(theirs)
    assert pynauty.autgrp(ours)[1:] == pynauty.autgrp(theirs)[1:]
    assert identity.edges_certificate(n, edges) == pynauty.certificate(theirs)


def test_the_contact_graph_of_a_cluster_is_its_contacts() -> None:
    c = CLUSTERS["polytetrahedron"]
    g = identity._nauty_graph(c)
    assert (g.number_of_vertices, g.directed, g.vertex_coloring) == (c.n, False, [])
    assert sorted((i, j) for i, js in g.adjacency_dict.items() for j in js) == list(c.contacts)


# --------------------------------------------------------------------------- symmetries


def bent_chain() -> Cluster:
    """A 4-sphere chain 0-1-2-3 with unit bonds and bond angles of 120 and 90 degrees: its contact graph has
    the reversal 0123 -> 3210 as an automorphism, which no isometry realises."""
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.5, np.sqrt(3.0) / 2.0, 0.0], [1.5, np.sqrt(3.0) / 2.0, 1.0]])
    return Cluster(x, ((0, 1), (1, 2), (2, 3)))


def _is_symmetry(c: Cluster, t: np.ndarray) -> bool:
    x = c.coords - c.coords.mean(axis=0)
    moved = {tuple(sorted((int(t[i]), int(t[j])))) for i, j in c.contacts}
    return moved == set(c.contacts) and kernels.aligned_max_error(x, x[t]) <= 1e-9


@pytest.mark.parametrize(
    "name,order",
    [("tetrahedron", 24), ("bipyramid", 12), ("octahedron", 48), ("chain60", 2), ("polytetrahedron", 4)],
)
def test_the_symmetries_of_clusters_whose_graph_automorphisms_are_all_isometries(name, order) -> None:
    c = CLUSTERS[name]
    group = symmetries(c, TOL_D)
    assert len(group) == len(automorphisms(c)) == order
    assert np.array_equal(group[0], np.arange(c.n))
    assert all(_is_symmetry(c, t) for t in group)


def test_a_graph_automorphism_that_moves_the_geometry_is_no_symmetry() -> None:
    c = bent_chain()
    assert len(automorphisms(c)) == 2
    assert symmetries(c, TOL_D).tolist() == [[0, 1, 2, 3]]
    assert not _is_symmetry(c, np.array([3, 2, 1, 0]))


def test_a_glued_cluster_without_symmetry_has_the_identity_only() -> None:
    c = CLUSTERS["glued10"]
    assert symmetries(c, TOL_D).tolist() == [list(range(c.n))]


@SETTINGS
@given(names, seeds, st.booleans())
def test_symmetries_follow_rotation_reflection_and_relabelling(name, seed, reflect) -> None:
    """The symmetries of a moved, mirrored and relabelled copy are the cluster's own, relabelled alike
    (new sphere k is old sphere perm[k]: t becomes inv[t[perm]]), and form a group."""
    c = CLUSTERS[name]
    rng = np.random.default_rng(seed)
    q = random_orthogonal(rng, reflect)
    perm = rng.permutation(c.n)
    moved = relabel(c, perm, c.coords @ q.T + rng.uniform(-5.0, 5.0, size=3))
    inv = np.argsort(perm)
    own = {tuple(inv[t[perm]].tolist()) for t in symmetries(c, TOL_D)}
    theirs = symmetries(moved, TOL_D)
    assert {tuple(t.tolist()) for t in theirs} == own
    assert all(_is_symmetry(moved, t) for t in theirs)
    keys = {t.tobytes() for t in theirs}
    assert all(s[t].tobytes() in keys for s in theirs for t in theirs)
