"""packings.workers.classify: static class, close-packed lattice type, describe()."""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packings.workers.classify import LATTICES, STATIC, describe, lattice_type, static_class
from packings.workers.cluster import contacts_from_coords, pair_distances
from packings.workers.seeds import seed_cluster
from tests.helpers import catalogue

S3 = np.sqrt(3.0)
LAYER = np.sqrt(2.0 / 3.0)
SHIFT = {"A": (0.0, 0.0), "B": (0.5, S3 / 6), "C": (1.0, S3 / 3)}


# --------------------------------------------------------------------------- constructions


def stacked(labels: str, radius: float) -> np.ndarray:
    """Close-packed layers with the given stacking (one letter per layer, heights
    0, sqrt(2/3), ...): the sites of each layer within ``radius`` (in-plane) of
    the centre of the A triangle at the origin."""
    centre = np.array([0.5, S3 / 6])
    pts = []
    for k, lab in enumerate(labels):
        sx, sy = SHIFT[lab]
        for i, j in itertools.product(range(-5, 6), repeat=2):
            xy = np.array([i + j / 2 + sx, j * S3 / 2 + sy])
            if np.linalg.norm(xy - centre) < radius:
                pts.append([xy[0], xy[1], k * LAYER])
    return np.array(pts)


def cubic_fcc(points) -> np.ndarray:
    """fcc sites given as integer vectors with even coordinate sum (conventional cube
    of side 2), scaled to unit nearest-neighbour distance."""
    p = np.array(points, dtype=float)
    assert np.all(p.sum(axis=1) % 2 == 0)
    return p / np.sqrt(2.0)


def cuboctahedron() -> np.ndarray:
    shell = [v for v in itertools.product([-1, 0, 1], repeat=3) if sum(map(abs, v)) == 2]
    return cubic_fcc([(0, 0, 0)] + shell)


def anticuboctahedron() -> np.ndarray:
    """Centre, its six neighbours in its layer (A), three above and three below in B."""
    centre = np.array([0.0, 0.0])
    layer = []
    for i, j in itertools.product(range(-2, 3), repeat=2):
        xy = np.array([i + j / 2, j * S3 / 2])
        if np.linalg.norm(xy - centre) < 1.01:
            layer.append([xy[0], xy[1], 0.0])
    assert len(layer) == 7
    layer.sort(key=lambda v: np.hypot(v[0], v[1]))  # the centre first
    caps = []
    for i, j in itertools.product(range(-2, 3), repeat=2):
        xy = np.array([i + j / 2 + 0.5, j * S3 / 2 + S3 / 6])
        if np.linalg.norm(xy) < 0.6:
            caps += [[xy[0], xy[1], LAYER], [xy[0], xy[1], -LAYER]]
    assert len(caps) == 6
    return np.array(layer + caps)


def octahedron() -> np.ndarray:
    """The 6 fcc sites around the octahedral hole (1, 0, 0) of the cubic cell."""
    return cubic_fcc([(0, 0, 0), (2, 0, 0), (1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1)])


def cube14() -> np.ndarray:
    """The conventional fcc cube: 8 corners and 6 face centres."""
    return cubic_fcc([v for v in itertools.product([0, 1, 2], repeat=3) if sum(v) % 2 == 0])


def trigonal_bipyramid() -> np.ndarray:
    """Two tetrahedra sharing a face: an A triangle with one sphere above and one below it (B)."""
    return np.vstack([stacked("A", 0.6), [[0.5, S3 / 6, LAYER], [0.5, S3 / 6, -LAYER]]])


def pentagonal_bipyramid() -> np.ndarray:
    r = 1.0 / (2.0 * np.sin(np.pi / 5))
    h = np.sqrt(1.0 - r * r)
    ring = [[r * np.cos(2 * np.pi * t / 5), r * np.sin(2 * np.pi * t / 5), 0.0] for t in range(5)]
    return np.array(ring + [[0, 0, h], [0, 0, -h]])


def icosahedron() -> np.ndarray:
    phi = (1 + np.sqrt(5)) / 2
    v = []
    for s1, s2 in itertools.product([-1, 1], repeat=2):
        v += [[0, s1, s2 * phi], [s1, s2 * phi, 0], [s2 * phi, 0, s1]]
    v = np.array(v) / np.linalg.norm([1, phi])
    return np.vstack([[0, 0, 0], v])


def hex_patch() -> np.ndarray:
    """A planar triangular patch of 10 spheres (a triangle of side 4) tilted in space."""
    pts = [[i + j / 2, j * S3 / 2, 0.0] for j in range(4) for i in range(4 - j)]
    q, _ = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))
    return np.array(pts) @ q.T + np.array([0.3, -2.0, 5.0])


def contacts(x: np.ndarray) -> tuple:
    return contacts_from_coords(x, 1e-5)


def classify(x: np.ndarray, **kw) -> str | None:
    return lattice_type(x, contacts(x), **kw)


def assert_valid_packing(x: np.ndarray) -> None:
    d = pair_distances(x)[np.triu_indices(len(x), 1)]
    assert d.min() > 1 - 1e-9


# Every constructed cluster with the answer expected, the number of spheres and contacts.
KNOWN = {
    "fcc ABC": (lambda: stacked("ABC", 1.0), "fcc", 11),
    "fcc ABC 13": (lambda: stacked("ABC", 1.05), "fcc", 13),
    "fcc ABCA": (lambda: stacked("ABCA", 1.0), "fcc", 14),
    "cuboctahedron": (cuboctahedron, "fcc", 13),
    "fcc cube": (cube14, "fcc", 14),
    "octahedron": (octahedron, "both", 6),
    "fcc ACB": (lambda: stacked("ACB", 1.0), "fcc", 11),
    "fcc CBA": (lambda: stacked("CBA", 1.0), "fcc", 11),
    "hcp ABA": (lambda: stacked("ABA", 1.0), "hcp", 11),
    "hcp ABAB": (lambda: stacked("ABAB", 0.6), "hcp", 8),
    "anticuboctahedron": (anticuboctahedron, "hcp", 13),
    "trigonal bipyramid": (lambda: trigonal_bipyramid(), "hcp", 5),
    "both AB": (lambda: stacked("AB", 1.2), "both", 13),
    "tetrahedron": (lambda: stacked("AB", 0.6), "both", 4),
    "random ABCB": (lambda: stacked("ABCB", 1.0), "random", 16),
    "random ABAC": (lambda: stacked("ABAC", 0.6), "random", 10),
    "2d patch": (hex_patch, "2d", 10),
    "2d layer": (lambda: stacked("A", 1.2), "2d", 6),
    "pentagonal bipyramid": (pentagonal_bipyramid, None, 7),
    "icosahedron": (icosahedron, None, 13),
}


@pytest.mark.parametrize("name", list(KNOWN))
def test_known_clusters(name):
    build, expected, n = KNOWN[name]
    x = build()
    assert len(x) == n
    assert_valid_packing(x)
    assert classify(x) == expected
    assert expected is None or expected in LATTICES


def test_constructions_are_what_they_claim():
    # the trigonal bipyramid sub-case: a triangle with one sphere directly above and one below
    x = KNOWN["trigonal bipyramid"][0]()
    assert len(contacts(x)) == 9
    assert np.isclose(pair_distances(x).max(), 2 * LAYER)
    # cuboctahedron and anticuboctahedron: 12 neighbours at distance 1 around sphere 0, 24 + 12 contacts
    for x in (cuboctahedron(), anticuboctahedron()):
        assert np.allclose(np.linalg.norm(x[1:] - x[0], axis=1), 1.0)
        assert len(contacts(x)) == 36
    # the cubic fcc pieces are not in the {111} orientation of stacked(): no contact
    # triangle is parallel to the xy plane (their normals are the cube diagonals)
    assert len(contacts(octahedron())) == 12
    for x in (octahedron(), cube14(), cuboctahedron()):
        cs = set(contacts(x))
        for (i, j), k in itertools.product(cs, range(len(x))):
            if (i, k) in cs and (j, k) in cs:
                nrm = np.cross(x[j] - x[i], x[k] - x[i])
                assert np.allclose(np.abs(nrm) / np.linalg.norm(nrm), 1 / S3)
    # icosahedron: the surface spheres are 1/(sin(2 pi / 5)) ~ 1.0515 apart, not touching
    d = pair_distances(icosahedron())[1:, 1:]
    assert np.isclose(d[d > 0].min(), 1 / np.sin(2 * np.pi / 5))
    # pentagonal bipyramid: the apexes are ~1.05 apart, not touching: 15 contacts
    assert len(contacts(pentagonal_bipyramid())) == 15


def test_icosahedron_has_no_contact_triangle_and_surface_contacts_do_not_help():
    x = icosahedron()
    assert len(contacts(x)) == 12  # only the centre touches
    # even with the surface pairs declared as contacts, the geometry is not close-packed
    assert lattice_type(x, contacts_from_coords(x, 0.06)) is None


@pytest.mark.parametrize("n", [8, 9, 10])
def test_seed_polytetrahedra_are_not_close_packed(n):
    """The seed glues each new sphere onto a contact triangle.  Its first five
    spheres are two tetrahedra sharing a face (a trigonal bipyramid): that is an
    hcp fragment (a triangle in layer B, one sphere above and one below in A).
    The sixth sphere caps a tilted face of the bipyramid, making a chain of
    three face-sharing tetrahedra: in a close-packed lattice two tetrahedra
    share a face only across a layer plane, and both shared faces cannot be
    parallel to the same layer plane, so from n = 6 on the seed is not a
    close-packed fragment (any sub-cluster of a fragment would be one)."""
    c = seed_cluster(n)
    assert lattice_type(c.coords, c.contacts) is None
    first5, first6 = c.coords[:5], c.coords[:6]
    assert len(contacts(first5)) == 9 and classify(first5) == "hcp"
    assert len(contacts(first6)) == 12 and classify(first6) is None


def test_perturbed_fcc_is_not_close_packed():
    x = stacked("ABC", 1.05)
    rng = np.random.default_rng(0)
    for _ in range(5):
        y = x + 1e-2 * rng.normal(size=x.shape) / np.sqrt(3)
        assert lattice_type(y, contacts_from_coords(y, 0.05)) is None
        assert lattice_type(y, contacts_from_coords(y, 0.05), tol=0.1) == "fcc"  # a loose tolerance accepts it
    # a perturbation below tol is accepted
    y = x + 1e-6 * rng.normal(size=x.shape)
    assert classify(y) == "fcc"


def test_one_displaced_sphere_is_rejected():
    x = stacked("ABA", 1.0)
    x[-1, 2] += 0.3  # lift one sphere of the top layer off its site
    assert classify(x) is None


def test_mixed_labels_in_a_layer_are_rejected():
    # a triangle on A sites and, in the same plane, a sphere on a B site: not one lattice
    x = np.vstack([stacked("A", 0.6), [[3.5, S3 / 6, 0.0]]])
    assert classify(x) is None
    assert brute_force(x) == set()
    x[3] = [3.0, 0.0, 0.0]  # the same sphere moved onto an A site
    assert classify(x) == "2d"


@pytest.mark.parametrize(
    "top, height, expected",
    [("A", 2, "hcp"), ("B", 2, "both"), ("C", 2, "both"), ("A", 3, "fcc"), ("B", 3, "hcp"), ("C", 3, "hcp")],
)
def test_layers_with_a_gap(top, height, expected):
    """Two triangles in layers 0 and ``height`` (nothing between; a disconnected cluster):
    in the frame of the triangles the empty layers can be filled as fcc or hcp only if the
    labels allow it (hcp: equal labels on layers of equal parity, different otherwise; fcc:
    label difference = +-height mod 3).  A/B and A/C two layers apart are fcc in that frame
    and also hcp seen from a tilted frame (confirmed by the brute-force search)."""
    triangle = stacked("A", 0.6)
    x = np.vstack([triangle, triangle + [*SHIFT[top], height * LAYER]])
    assert classify(x) == expected
    assert brute_force(x) == EXPECTED_MEMBERSHIP[expected]


@pytest.mark.parametrize(
    "layers, labels, expected",
    [
        ("0123", "ABCA", (True, True, False)),
        ("0123", "ACBA", (True, True, False)),
        ("0123", "ABAB", (True, False, True)),
        ("01", "CA", (True, True, True)),
        ("0123", "ABCB", (True, False, False)),
        ("0123", "ABAC", (True, False, False)),
        ("012", "AAB", (False, False, False)),
        ("02", "AA", (True, False, True)),
        ("02", "AC", (True, True, False)),
        ("03", "AA", (True, True, False)),
        ("03", "AB", (True, False, True)),
        ("35", "BB", (True, False, True)),
    ],
)
def test_stacking_rules(layers, labels, expected):
    """The label-sequence rules on their own (one sphere per layer, in a fixed frame)."""
    from packings.workers.classify import _stacking

    k = np.array([int(c) for c in layers] * 2)
    lab = np.array(["ABC".index(c) for c in labels] * 2)
    assert _stacking(k, lab)[:3] == expected
    assert _stacking(np.append(k, k[0]), np.append(lab, (lab[0] + 1) % 3)) is None  # a mixed layer


def test_tiny_and_triangle_free_clusters():
    assert lattice_type(np.zeros((1, 3)), []) == "2d"
    assert lattice_type(np.array([[0, 0, 0], [1.0, 0, 0]]), [(0, 1)]) == "2d"
    assert lattice_type(np.array([[0, 0, 0], [1.5, 0, 0]]), []) is None
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]])
    assert lattice_type(square, contacts(square)) is None  # no contact triangle


# --------------------------------------------------------------------------- brute force cross-check


def _lattice_sites(kind: str, reach: int = 4) -> np.ndarray:
    """fcc (cubic construction) or hcp (hexagonal cell with a two-site basis) around the origin."""
    r = range(-reach, reach + 1)
    if kind == "fcc":
        span = range(-2 * reach, 2 * reach + 1)
        return cubic_fcc([v for v in itertools.product(span, repeat=3) if sum(v) % 2 == 0])
    a1, a2, c = np.array([1.0, 0, 0]), np.array([0.5, S3 / 2, 0]), np.array([0, 0, 2 * LAYER])
    basis = [np.zeros(3), np.array([0.5, S3 / 6, LAYER])]
    return np.array([i * a1 + j * a2 + k * c + b for i in r for j in r for k in r for b in basis])


def _member(x: np.ndarray, sites: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether x maps into ``sites`` by an isometry sending its first contact triangle onto a
    nearest-neighbour triangle at the origin (every site of fcc/hcp is equivalent)."""
    tri = None
    cs = contacts(x)
    for i, j in cs:
        for k in range(j + 1, len(x)):
            if (i, k) in cs and (j, k) in cs:
                tri = (i, j, k)
                break
        if tri:
            break
    assert tri is not None
    sites = sites[np.linalg.norm(sites, axis=1) < 2 * len(x)]
    nn = sites[np.abs(np.linalg.norm(sites, axis=1) - 1) < 1e-9]
    src = x[list(tri)] - x[tri[0]]
    for u, v in itertools.permutations(nn, 2):
        if abs(np.linalg.norm(u - v) - 1) > 1e-9:
            continue
        dst = np.array([np.zeros(3), u, v])
        # the two isometries mapping the triangle: add the normals as a fourth point
        for sign in (1, -1):
            s4 = np.vstack([src, np.cross(src[1], src[2])])
            d4 = np.vstack([dst, sign * np.cross(dst[1], dst[2])])
            q, *_ = np.linalg.lstsq(s4, d4, rcond=None)
            y = (x - x[tri[0]]) @ q
            d = np.linalg.norm(y[:, None, :] - sites[None, :, :], axis=2).min(axis=1)
            if d.max() < tol:
                return True
    return False


def brute_force(x: np.ndarray) -> set[str]:
    return {kind for kind in ("fcc", "hcp") if _member(x, _lattice_sites(kind))}


EXPECTED_MEMBERSHIP = {"fcc": {"fcc"}, "hcp": {"hcp"}, "both": {"fcc", "hcp"}, "2d": {"fcc", "hcp"}}


@pytest.mark.parametrize("name", [k for k in KNOWN if KNOWN[k][1] is not None or k == "pentagonal bipyramid"])
def test_brute_force_agrees_on_constructions(name):
    build, expected, _ = KNOWN[name]
    assert brute_force(build()) == EXPECTED_MEMBERSHIP.get(expected, set())


def test_brute_force_agrees_on_enumerated_clusters_n8():
    cat = catalogue(8)
    labels = []
    for c in cat.clusters:
        label = lattice_type(c.coords, c.contacts)
        labels.append(label)
        assert brute_force(c.coords) == EXPECTED_MEMBERSHIP.get(label, set())
    assert any(label is None for label in labels) and any(label is not None for label in labels)


# --------------------------------------------------------------------------- invariance


def _random_isometry(seed: int, reflect: bool) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    if reflect:
        q = q @ np.diag([1.0, 1.0, -1.0])
    return q, rng.uniform(-10, 10, size=3)


@settings(max_examples=80, deadline=None)
@given(
    name=st.sampled_from(list(KNOWN)),
    seed=st.integers(0, 2**32 - 1),
    reflect=st.booleans(),
    data=st.data(),
)
def test_label_invariant_under_isometry_and_relabelling(name, seed, reflect, data):
    build, expected, n = KNOWN[name]
    x = build()
    cs = contacts(x)
    perm = np.array(data.draw(st.permutations(range(n))))  # new sphere t is old sphere perm[t]
    inverse = np.argsort(perm)
    q, t = _random_isometry(seed, reflect)
    y = x[perm] @ q.T + t
    cs2 = [(int(inverse[i]), int(inverse[j])) for i, j in cs]
    for i, j in cs2:
        assert abs(np.linalg.norm(y[i] - y[j]) - 1) < 1e-5
    assert lattice_type(y, cs2) == expected
    assert describe(y, cs2)["lattice"] == expected


# --------------------------------------------------------------------------- static, describe


@pytest.mark.parametrize(
    "n, m, expected",
    [
        (4, 6, "isostatic"),
        (10, 23, "hypostatic"),
        (10, 24, "isostatic"),
        (10, 25, "hyperstatic"),
        (13, 36, "hyperstatic"),
        (3, 3, "isostatic"),
        (3, 2, "hypostatic"),
    ],
)
def test_static_class(n, m, expected):
    assert static_class(n, m) == expected
    assert expected in STATIC


def test_describe_trigonal_bipyramid():
    x = KNOWN["trigonal bipyramid"][0]()
    d = describe(x, contacts(x))
    # the two apexes are 2 sqrt(2/3) apart; every other pair touches
    assert d == {
        "static": "isostatic",
        "excess": 0,
        "lattice": "hcp",
        "close_packed": True,
        "min_gap": pytest.approx(2 * np.sqrt(2 / 3) - 1, abs=1e-12),
    }


def test_describe_rhombus_and_complete_cluster():
    rhombus = np.array([[0, 0, 0], [1, 0, 0], [0.5, S3 / 2, 0], [1.5, S3 / 2, 0]])
    d = describe(rhombus, contacts(rhombus))
    assert d["static"] == "hypostatic" and d["excess"] == -1  # m = 5 < 3n - 6 = 6
    assert d["min_gap"] == pytest.approx(S3 - 1)
    assert d["lattice"] == "2d" and d["close_packed"]
    tet = stacked("AB", 0.6)
    d = describe(tet, contacts(tet))
    assert d["min_gap"] is None and d["excess"] == 0 and d["lattice"] == "both"
    d = describe(icosahedron(), contacts(icosahedron()))
    assert d["static"] == "hypostatic" and d["excess"] == 12 - 33 and not d["close_packed"]
    assert d["min_gap"] == pytest.approx(1 / np.sin(2 * np.pi / 5) - 1)


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(list(KNOWN)), seed=st.integers(0, 2**32 - 1), scale=st.floats(0.0, 3.0))
def test_the_distance_prefilter_rejects_only_what_the_frames_reject(name, seed, scale):
    """The cheap rejection (a pair distance farther than 2 tol from every sqrt(k/3)) never changes the
    answer: constructed clusters moved by up to 3 tol (so that some stay close-packed and some do not),
    with and without it."""
    import packings.workers.classify as classify

    build, _, n = KNOWN[name]
    x = build()
    rng = np.random.default_rng(seed)
    u = rng.normal(size=x.shape)
    y = x + scale * 1e-4 * u / np.linalg.norm(u, axis=1, keepdims=True) * rng.uniform(0, 1, size=(n, 1))
    cs = contacts(x)
    with_filter = lattice_type(y, cs)
    real = classify._off_lattice_distance
    classify._off_lattice_distance = lambda p, tol: False
    try:
        without = lattice_type(y, cs)
    finally:
        classify._off_lattice_distance = real
    assert with_filter == without


def test_the_distance_prefilter_passes_close_packed_and_catches_others():
    import packings.workers.classify as classify

    for name, (build, expected, _) in KNOWN.items():
        if expected is not None:
            assert not classify._off_lattice_distance(build(), 1e-4), name
    assert classify._off_lattice_distance(icosahedron(), 1e-4)
    assert classify._off_lattice_distance(pentagonal_bipyramid(), 1e-4)
