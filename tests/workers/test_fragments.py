"""packings.workers.fragments: every close-packed fragment of n spheres with at least M contacts."""

import functools
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packings.workers import fragments as F
from packings.workers.catalysis import remainder
from packings.workers.classify import lattice_type
from packings.workers.cluster import Cluster, contacts_from_coords
from packings.workers.identity import ClusterIndex, certificate_key
from packings.workers.params import Params

P = Params()
DATA = Path(__file__).parent.parent / "data"


# ----------------------------------------------------------------- the canonical form of a fragment
# fragments._grown (compiled) moves each fragment so, as these do one tuple at a time.


def _canonical(sites) -> tuple[int, ...]:
    """The fragment moved within its layers (by a lattice vector) so that its first site is at (0, 0)."""
    first = min(sites)
    shift = first % (F._S * F._S) - (F._O * F._S + F._O)
    return tuple(sorted(q - shift for q in sites))


def _canonical_stack(positions: tuple[int, ...], sites) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The fragment moved so that its lowest layer is in position A (every layer moved by the same third of
    a lattice vector) and its first site is at (0, 0) (:func:`_canonical`)."""
    p0 = positions[0]
    if p0:
        # layer position p becomes p - p0; where that is negative, + 3, and the site moves by -(a1 + a2)
        sites = [q - (F._S + 1 if positions[q // (F._S * F._S)] < p0 else 0) for q in sites]
        positions = tuple((p - p0) % 3 for p in positions)
    return positions, _canonical(sites)


def _grow_stacks(n: int, t: list[int], most_layers: int) -> dict[tuple[tuple[int, ...], tuple[int, ...]], int]:
    """F._grown as {(positions of its layers, sites): contacts}, in the order the fragments were made."""
    rows, contacts = F._grown(n, t, most_layers)
    return {
        (tuple(int(p) for p in row[:most_layers] if p >= 0), tuple(int(q) for q in row[most_layers:])): int(c)
        for row, c in zip(rows, contacts)
    }


# ----------------------------------------------------------------- the reference: one structure at a time
# Every structure of ``layers`` layers, one stacking sequence after another, each grown on its own with the
# twelve touching sites of every site: what fragments._grown must find, more slowly.


def sequences(layers: int) -> list[tuple[int, ...]]:
    """The stacking sequences of ``layers`` layers beginning with A (0), adjacent layers different."""
    return [
        s for s in itertools.product(range(3), repeat=layers) if s[0] == 0 and all(a != b for a, b in zip(s, s[1:]))
    ]


def _position(seq: tuple[int, ...], site: int) -> np.ndarray:
    layer, rest = divmod(site, F._S * F._S)
    i, j = divmod(rest, F._S)
    p = (i - F._O) * F._A1 + (j - F._O) * F._A2 + F._SHIFT[seq[layer]]
    return np.array([p[0], p[1], layer * F._H])


@functools.lru_cache(maxsize=None)
def _steps(seq: tuple[int, ...]) -> tuple[tuple[int, ...], ...]:
    """For each layer, the site offsets of its twelve (fewer at the ends of the stack) touching sites."""
    origin = F._O * F._S + F._O
    out = []
    for layer in range(len(seq)):
        here = _position(seq, layer * F._S * F._S + origin)
        out.append(
            tuple(
                dl * F._S * F._S + di * F._S + dj
                for dl in (-1, 0, 1)
                if 0 <= layer + dl < len(seq)
                for di in range(-2, 3)
                for dj in range(-2, 3)
                if (dl, di, dj) != (0, 0, 0)
                and abs(
                    np.linalg.norm(_position(seq, (layer + dl) * F._S * F._S + origin + di * F._S + dj) - here) - 1.0
                )
                < 1e-9
            )
        )
    return tuple(out)


def _grow(seq: tuple[int, ...], n: int, t: list[int]) -> dict[tuple[int, ...], int]:
    """Every connected fragment of n sites of the structure ``seq`` reached through fragments meeting the
    thresholds ``t``, up to moves within the layers: {sites: contacts}."""
    steps = _steps(seq)
    level = {_canonical([layer * F._S * F._S + F._O * F._S + F._O]): 0 for layer in range(len(seq))}
    for k in range(2, n + 1):
        grown: dict[tuple[int, ...], int] = {}
        for frag, c in level.items():
            inside = set(frag)
            gain: dict[int, int] = {}
            for u in frag:
                for d in steps[u // (F._S * F._S)]:
                    q = u + d
                    if q not in inside:
                        gain[q] = gain.get(q, 0) + 1
            for q, g in gain.items():
                if c + g >= t[k]:
                    grown.setdefault(_canonical(frag + (q,)), c + g)
        level = grown
    return level


def _grow_stacks_dict(n: int, t: list[int], most_layers: int) -> dict[tuple[tuple[int, ...], tuple[int, ...]], int]:
    """The growth of F._grown as a dictionary of tuples, one fragment at a time in Python (the code the
    compiled growth replaced): {(positions of its layers, sites): contacts}, in the order first made."""
    level = {((0,), _canonical([F._O * F._S + F._O])): 0}
    for k in range(2, n + 1):
        grown: dict = {}
        for (positions, frag), c in level.items():
            inside = set(frag)
            height = len(positions)
            gain: dict = {}  # (position of a new layer or None, -1 below / 1 above, site) -> contacts it makes
            for u in frag:
                layer = u // (F._S * F._S)
                for di, dj in F._IN_LAYER:
                    q = u + di * F._S + dj
                    if q not in inside:
                        gain[None, 0, q] = gain.get((None, 0, q), 0) + 1
                for dl in (-1, 1):
                    other = layer + dl
                    if 0 <= other < height:
                        for di, dj in F._across(positions[layer], positions[other]):
                            q = u + dl * F._S * F._S + di * F._S + dj
                            if q not in inside:
                                gain[None, 0, q] = gain.get((None, 0, q), 0) + 1
                    elif height < most_layers:  # a new layer, above or below, in either free position
                        for p in range(3):
                            if p != positions[layer]:
                                for di, dj in F._across(positions[layer], p):
                                    key = (p, dl, u + max(dl, 0) * F._S * F._S + di * F._S + dj)
                                    gain[key] = gain.get(key, 0) + 1
            for (p, dl, q), g in gain.items():
                if c + g < t[k]:
                    continue
                if p is None:
                    key = (positions, _canonical(frag + (q,)))
                elif dl == 1:  # above
                    key = _canonical_stack(positions + (p,), frag + (q,))
                else:  # below: every layer goes up one, q is in the new layer 0
                    key = _canonical_stack((p,) + positions, tuple(v + F._S * F._S for v in frag) + (q,))
                grown.setdefault(key, c + g)
        level = grown
    return level


def _all_connected(n: int, min_contacts: int) -> set[bytes]:
    """The keys of every connected fragment of n sites with at least ``min_contacts`` contacts, grown
    without thresholds (every connected fragment is kept at every size), in the same structures."""
    keys = set()
    for seq in sequences(F.max_layers(n, min_contacts)):
        grown = _grow(seq, n, [0] * (n + 1))
        frags = np.array([f for f, c in grown.items() if c >= min_contacts], dtype=np.int64).reshape(-1, n)
        keys.update(F._keys(F._coordinates(seq, frags)))
    return keys


@pytest.mark.parametrize("n, m", [(5, 7), (6, 11), (6, 12)])
def test_the_thresholds_lose_no_fragment(n, m):
    """The thresholds keep every fragment that growing every connected fragment finds."""
    got = {F._keys(f.cluster.coords[None])[0] for f in F.close_packed(n, m)}
    assert got == _all_connected(n, m) and got


@pytest.mark.parametrize("n, m", [(7, 13), (8, 15)])
def test_growing_the_stacks_finds_what_growing_each_sequence_finds(n, m):
    """F._grown (a layer's position chosen as it is entered) and _grow over every sequence of
    max_layers layers, with the same thresholds, give the same fragments."""
    t = F.thresholds(n, m)
    per_sequence = set()
    for seq in sequences(F.max_layers(n, m)):
        frags = np.array(list(_grow(seq, n, t)), dtype=np.int64).reshape(-1, n)
        per_sequence.update(F._keys(F._coordinates(seq, frags)))
    stacks = set()
    for positions, frag in _grow_stacks(n, t, F.max_layers(n, m)):
        stacks.update(F._keys(F._coordinates(positions, np.array([frag], dtype=np.int64))))
    assert stacks == per_sequence and len(stacks) > 10


@pytest.mark.parametrize("n, m", [(1, 0), (2, 1), (6, 11), (7, 13), (8, 15), (9, 18)])
def test_the_compiled_growth_makes_the_dictionarys_fragments_in_its_order(n, m):
    """F._grown (rows of integers in a hash table, compiled) and the dictionary of tuples give the same
    fragments with the same contacts, made in the same order (the listing's order and representatives)."""
    t = F.thresholds(n, m)
    want = _grow_stacks_dict(n, t, F.max_layers(n, m))
    got = _grow_stacks(n, t, F.max_layers(n, m))
    assert list(got.items()) == list(want.items()) and want


def test_the_compiled_growth_grows_its_table():
    """Many more fragments of one size than the last (a table that starts at twice the parents and doubles):
    every fragment kept once, in the dictionary's order."""
    n, t = 6, [0] * 7
    rows, contacts = F._grown(n, t, 3)
    want = _grow_stacks_dict(n, t, 3)
    assert len(rows) == len(want) > 4 * 1024
    assert len({r.tobytes() for r in rows}) == len(rows)
    assert list(_grow_stacks(n, t, 3).items()) == list(want.items())


def test_no_fragment_can_have_more_contacts_than_the_layers_allow():
    assert _grow_stacks(13, F.thresholds(13, 39), F.max_layers(13, 39)) == {} and F.close_packed(13, 39) == []


def test_no_fragment_spans_more_layers_than_the_bound_allows():
    """Grown in structures of two layers more than max_layers, nothing with so many contacts spans them."""
    n, m = 6, 11
    layers = F.max_layers(n, m)
    for seq in sequences(layers + 2)[:3]:
        for frag, c in _grow(seq, n, [0] * (n + 1)).items():
            spanned = len({q // (F._S * F._S) for q in frag})
            assert c <= F.layer_bound(n, spanned)
            if spanned > layers:
                assert c < m


def test_layer_bound_small_cases():
    assert F.layer_bound(4, 2) == 6  # the tetrahedron: a triangle and one sphere on it
    assert F.layer_bound(6, 2) == 12  # the octahedron: two triangles
    assert F.layer_bound(7, 1) == 12  # the hexagon with its centre
    assert F.layer_bound(3, 4) == -1
    assert max(F.layer_bound(13, L) for L in range(1, 14)) == 38  # an upper bound: the most is 36
    assert F.max_layers(13, 39) == 0 and F.max_layers(13, 32) == 6
    with pytest.raises(ValueError):
        F.close_packed(31, 90)


def test_thresholds():
    t = F.thresholds(13, 32)
    assert t[13] == 32 and t[1] == 0
    assert all(a <= b for a, b in zip(t, t[1:]))
    for k in range(2, 14):  # a fragment of k with c >= t[k] has a sphere of degree <= 2c/k; without it, >= t[k-1]
        assert all(c - (2 * c) // k >= t[k - 1] for c in range(t[k], 3 * k))


def test_octahedron_and_the_fragments_of_six():
    """Six spheres with 12 contacts: the octahedron is the one close-packed fragment (the other rigid cluster,
    three tetrahedra about an edge, is not close-packed); with 11 contacts none is rigid."""
    six = F.close_packed(6, 12)
    assert len(six) == 1 and six[0].cluster.m == 12
    assert lattice_type(six[0].cluster.coords, six[0].cluster.contacts) == "both"  # two layers: fcc and hcp
    assert all(not remainder(f.cluster, (), P).rigid for f in F.close_packed(6, 11) if f.cluster.m == 11)


def test_fragments_are_distinct_close_packed_and_keep_their_contacts():
    frags = F.close_packed(8, 15)
    index = ClusterIndex()
    for f in frags:
        c = f.cluster
        assert c.m >= 15 and c.contacts == contacts_from_coords(c.coords, P.tol_a)
        assert lattice_type(c.coords, c.contacts) in ("fcc", "hcp", "both", "random", "2d")
        assert index.add(c, P.tol_d)[1]  # the identity tells every two apart
        assert len(f.stacking) >= 1 and all(a != b for a, b in zip(f.stacking, f.stacking[1:]))


_ANGLES = st.floats(min_value=-np.pi, max_value=np.pi, allow_nan=False)


@settings(max_examples=25, deadline=None)
@given(a=_ANGLES, b=_ANGLES, c=_ANGLES, reflect=st.booleans(), seed=st.integers(0, 2**31 - 1))
def test_key_is_invariant_under_rotation_reflection_translation_and_relabelling(a, b, c, reflect, seed):
    frags = F.close_packed(7, 14)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    q = rx @ ry @ rz @ np.diag([1.0, 1.0, -1.0 if reflect else 1.0])
    perm = np.random.default_rng(seed).permutation(7)
    x = np.array([f.cluster.coords for f in frags])
    y = (x @ q.T + np.array([0.3, -2.0, 5.0]))[:, perm]
    assert F._keys(x) == F._keys(y)
    assert len(set(F._keys(x))) == len(frags)


def test_sorted_distances_alone_would_merge_two_fragments():
    """Two close-packed fragments of 11 (26 contacts each) whose sorted pair distances are the same sphere by
    sphere, with different contact graphs: the key keeps both apart."""
    data = json.loads((DATA / "n11_homometric.json").read_text())["clusters"]
    a, b = (Cluster(np.array(d["coords"]), tuple(map(tuple, d["contacts"]))) for d in data)

    def rows(c):
        d = np.sort(np.linalg.norm(c.coords[:, None] - c.coords[None], axis=-1).round(6), axis=1)
        return d[np.lexsort(d.T[::-1])]

    assert np.array_equal(rows(a), rows(b))
    assert certificate_key(a) != certificate_key(b)
    assert F._keys(a.coords[None]) != F._keys(b.coords[None])


def test_the_lost_cluster_of_11_is_a_close_packed_fragment():
    """Among the close-packed fragments of 11 with at least 26 contacts is the cluster no path reaches
    (tests/data/n11_catalysis.json), rigid by the endpoint rule."""
    data = json.loads((DATA / "n11_catalysis.json").read_text())
    found = [
        r
        for r in (remainder(f.cluster, (), P) for f in F.close_packed(11, 26))
        if r.rigid and certificate_key(r.cluster) == data["certificate"]
    ]
    assert len(found) == 1
    assert (found[0].cluster.m, lattice_type(found[0].cluster.coords, found[0].cluster.contacts)) == (26, "hcp")
