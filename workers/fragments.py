"""Close-packed fragments: every set of n sites of a close-packed structure with at least M contacts.

Numpy, and numba for the growth (:mod:`packings.workers._growth`); no database or Dask imports.

Why.  The path enumeration finds the rigid clusters connected to its seed by one-dimensional paths,
and some clusters are reached by none (docs/method.md): at n = 11 a fragment of the
hcp lattice with 26 contacts from which every broken contact leaves a set of dimension 0 or 2.
Catalysis finds such clusters from the clusters of n + 1, or by moving one sphere of the stored
clusters of n; this module lists the close-packed ones directly, for any n, without a catalogue.

Structures.  A close-packed structure is a stack of triangular layers of unit spacing,
sqrt(2/3) apart, each layer in one of the three positions A, B, C of the plane, and two adjacent
layers in different positions: fcc is ABCABC..., hcp ABAB..., every other sequence a random
stacking.  A fragment of n spheres whose centres span L consecutive layers lies in the structure of
L layers with some sequence; every sequence beginning with A is tried (moving every layer by a third
of a lattice vector turns A into B, B into C and C into A, so any other sequence is one of those,
moved).  Only spheres in adjacent layers or in one layer can touch (layers two apart are
2 sqrt(2/3) > 1 apart), so the contacts of a fragment with n_1 ... n_L spheres in its layers are at
most the sum of

* within a layer of a spheres: 3a - sqrt(12a - 3), rounded down, the most unit distances among a
  points of the triangular lattice (Harborth, Elem. Math. 29, 1974);
* between adjacent layers of a and b spheres: their contacts form a subgraph of the honeycomb
  lattice (the sites of one layer and the hollows of it that the next layer covers), planar with
  girth 6, so at most max(a + b - 1, 3(a + b - 2) / 2) edges, and at most 3 min(a, b) (a sphere
  touches at most three of an adjacent layer).

:func:`layer_bound` maximises that over n_1 + ... + n_L = n; a fragment with at least M contacts
spans at most :func:`max_layers` layers.  The growth (:func:`_grown`) chooses the position of a
layer when the first sphere enters it, so that a fragment is grown once for each sequence of the
layers it spans, not again in every longer structure that holds it (growing every structure of
one sequence after another is the reference it is tested against, in the tests).  Each size is held
as rows of small integers in a hash table, grown by compiled code (:mod:`packings.workers._growth`):
about 120 bytes a fragment of 19 sites (a row of 23 four-byte integers, its contacts and its share of
the table), against about 750 in a dictionary of tuples.

Growth.  Fragments are grown from one site, a touching site at a time, keeping at size k only those
with at least T(k) contacts (:func:`thresholds`).  T(n) = M, and T(k - 1) = T(k) - floor(2 T(k) / k):
a fragment of k spheres with c >= T(k) contacts has a sphere of at most the average degree
floor(2c / k), and without it c - floor(2c / k) >= T(k - 1) contacts are left.  So every fragment with
at least M contacts is reached through fragments that meet the thresholds, provided that at each
size one of its spheres of at most average degree leaves the rest connected (growth adds touching
sites only).  That proviso is the method's one assumption: for a disconnected remainder a sphere
must join two pieces that touch it, which takes a cut sphere of least degree in a fragment dense
enough to meet the thresholds.  The tests compare with every connected fragment, unfiltered, for
small n.

Fragments are told apart by a congruence invariant (:func:`_keys`: for each sphere, its distances
to the others, each with that other sphere's own sorted distances): the same for congruent
fragments, however placed and numbered.  Sorted distances alone are not enough: at n = 11, two of
the 790 fragments with at least 26 contacts that the identity tells apart have the same sorted
distances sphere by sphere.  What is stored is decided by the identity of the catalogue
(:mod:`packings.workers.identity`), not by this key.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from packings.workers import kernels
from packings.workers.cluster import Cluster, contacts_from_coords, triangles
from packings.workers.params import DEFAULT, Params

_S = 64  #: site (layer l, i, j) is the integer l S^2 + (i + _O) S + (j + _O)
_O = _S // 2
_H = math.sqrt(2.0 / 3.0)  #: the spacing of the layers
_A1, _A2 = np.array([1.0, 0.0]), np.array([0.5, math.sqrt(3.0) / 2.0])
_SHIFT = {0: np.zeros(2), 1: (_A1 + _A2) / 3.0, 2: 2.0 * (_A1 + _A2) / 3.0}  #: positions A, B, C of a layer


def _in_layer(a: int) -> int:
    """The most contacts among a spheres of one triangular layer (Harborth)."""
    return 0 if a <= 1 else math.floor(3 * a - math.sqrt(12 * a - 3) + 1e-9)


def _between(a: int, b: int) -> int:
    """At most how many contacts a spheres of one layer have with b of the next (module doc)."""
    if a == 0 or b == 0:
        return 0
    return min(a * b, 3 * min(a, b), max(a + b - 1, (3 * (a + b - 2)) // 2))


@functools.lru_cache(maxsize=None)
def layer_bound(n: int, layers: int) -> int:
    """At most how many contacts n spheres in exactly ``layers`` consecutive layers of a close-packed
    structure have (-1 if they cannot: fewer spheres than layers)."""
    if layers < 1 or n < layers:
        return -1

    @functools.lru_cache(maxsize=None)
    def best(left: int, layers_left: int, last: int) -> int:  # the rest, after a layer of ``last`` spheres
        if layers_left == 0:
            return 0 if left == 0 else -(10**9)
        return max(
            _in_layer(a) + _between(last, a) + best(left - a, layers_left - 1, a)
            for a in range(1, left - layers_left + 2)
        )

    return best(n, layers, 0)


def max_layers(n: int, min_contacts: int) -> int:
    """The most layers a fragment of n spheres with at least ``min_contacts`` contacts can span (0: none
    can have so many)."""
    return max((L for L in range(1, n + 1) if layer_bound(n, L) >= min_contacts), default=0)


def thresholds(n: int, min_contacts: int) -> list[int]:
    """T(0), ..., T(n): the fewest contacts a fragment of k spheres may have to grow into one of n spheres
    with at least ``min_contacts`` (module doc)."""
    t = [0] * (n + 1)
    t[n] = min_contacts
    for k in range(n, 1, -1):
        t[k - 1] = max(0, t[k] - (2 * t[k]) // k)
    return t


_IN_LAYER = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, -1), (-1, 1))  #: (di, dj) of the six touching sites of a layer


@functools.lru_cache(maxsize=None)
def _across(p: int, q: int) -> tuple[tuple[int, int], ...]:
    """(di, dj) of the three sites of a layer in position q touching a site of the adjacent layer in position p."""
    return tuple(
        (di, dj)
        for di in range(-2, 3)
        for dj in range(-2, 3)
        if abs(np.linalg.norm(np.append(di * _A1 + dj * _A2 + _SHIFT[q] - _SHIFT[p], _H)) - 1.0) < 1e-9
    )


def _grown(n: int, t: list[int], most_layers: int) -> tuple[np.ndarray, np.ndarray]:
    """Every connected fragment of n sites of any close-packed structure spanning at most ``most_layers``
    layers, reached through fragments meeting the thresholds ``t``, once for each sequence of the layers
    it spans: (rows, contacts), a row being the positions of its layers (-1 past its height,
    ``most_layers`` columns) and then its sites in increasing order, moved so that its lowest layer is
    in position A (every layer by the same third of a lattice vector: a layer in position p goes to
    p - p0 mod 3, and where p < p0 its sites move by -(a1 + a2)) and its first site is at (0, 0) of
    its layer (every site by the same lattice vector).
    The same fragments as growing every sequence's structure on its own, without growing each again in
    every longer sequence that holds it: a layer's position is chosen when the first site enters it.
    Grown one size at a time by :func:`packings.workers._growth.grow` (compiled; the order in which
    fragments are first made is kept, so the listing does not depend on how they are stored)."""
    from packings.workers import _growth

    if most_layers < 1:  # no fragment of n can have so many contacts
        return np.zeros((0, n), dtype=np.int32), np.zeros(0, dtype=np.int64)
    rows = np.full((1, most_layers + 1), -1, dtype=np.int32)
    rows[0, 0], rows[0, most_layers] = 0, _O * _S + _O
    contacts = np.zeros(1, dtype=np.int64)
    in_layer, across = _offsets()
    for k in range(2, n + 1):
        rows, contacts = _growth.grow(rows, contacts, most_layers, t[k], in_layer, across, _S, _O)
    return rows, contacts


@functools.lru_cache(maxsize=None)
def _offsets() -> tuple[np.ndarray, np.ndarray]:
    """The site offsets di S + dj of the touching sites, as :func:`packings.workers._growth.grow` takes them:
    the six of a layer, in the order of _IN_LAYER, and the three of a layer in position q from one in p
    (3 x 3 x 3, in the order of :func:`_across`; zero where p = q)."""
    in_layer = np.array([di * _S + dj for di, dj in _IN_LAYER], dtype=np.int64)
    across = np.zeros((3, 3, 3), dtype=np.int64)
    for p in range(3):
        for q in range(3):
            if p != q:
                across[p, q] = [di * _S + dj for di, dj in _across(p, q)]
    return in_layer, across


@dataclass(frozen=True)
class Fragment:
    """A close-packed fragment: its spheres (the cluster, in the frame of its first contact triangle) and
    the positions of the layers it spans where it was first found (0, 1, 2 for A, B, C)."""

    cluster: Cluster
    stacking: tuple[int, ...]


_W = np.random.default_rng(20161).integers(1, 2**62, size=(2, 64), dtype=np.int64)  #: fixed hash weights


def _keys(x: np.ndarray) -> list[bytes]:
    """A congruence invariant of each point set x[b] (B x n x 3): for each point, its pair distances (exact
    on the lattice, rounded to 1e-6) each paired with the other point's sorted distances, sorted; then
    those sorted; rows hashed into 64 bits on the way (wrapping integer sums with fixed weights).
    Congruent sets, however placed, reflected and numbered, have the same key."""
    n = x.shape[1]
    d = np.rint(np.sqrt(((x[:, :, None] - x[:, None]) ** 2).sum(axis=-1)) * 1e6).astype(np.int64)
    with np.errstate(over="ignore"):
        own = (np.sort(d, axis=2) * _W[0, :n]).sum(axis=2)  # each point's sorted distances, hashed
        pairs = np.sort(d * np.int64(1_000_003) + own[:, None, :], axis=2)
        rows = np.sort((pairs * _W[1, :n]).sum(axis=2), axis=1)
    return [r.tobytes() for r in rows]


def _coordinates(seq: tuple[int, ...], frags: np.ndarray) -> np.ndarray:
    """The centres (B x n x 3) of fragments given by their sites (B x n)."""
    layer, rest = np.divmod(frags, _S * _S)
    i, j = np.divmod(rest, _S)
    shift = np.array([_SHIFT[p] for p in seq])[layer]
    plane = (i - _O)[..., None] * _A1 + (j - _O)[..., None] * _A2 + shift
    return np.concatenate([plane, (layer * _H)[..., None]], axis=-1)


def close_packed(n: int, min_contacts: int, params: Params = DEFAULT) -> list[Fragment]:
    """Every close-packed fragment of n spheres with at least ``min_contacts`` contacts, once each up to
    congruence (module doc), in the order found (:func:`_grown`, by the sequence of the layers it
    spans)."""
    if not 1 <= n <= 30:
        raise ValueError(f"n must be between 1 and 30, got {n}")
    most = max_layers(n, min_contacts)
    rows, _ = _grown(n, thresholds(n, min_contacts), most)
    by_stack: dict[tuple[int, ...], list[int]] = {}
    for r, row in enumerate(rows[:, :most].tolist()):
        by_stack.setdefault(tuple(p for p in row if p >= 0), []).append(r)
    seen: set[bytes] = set()
    out = []
    for positions, members in sorted(by_stack.items()):
        frags = rows[members, most:].astype(np.int64)
        for a in range(0, len(frags), 4096):
            x = _coordinates(positions, frags[a : a + 4096])
            for key, xb in zip(_keys(x), x):
                if key in seen:
                    continue
                seen.add(key)
                contacts = contacts_from_coords(xb, params.tol_a)
                tri = triangles(contacts)
                xb = xb - xb.mean(axis=0)
                out.append(Fragment(Cluster(kernels.to_frame(xb, tri[0]) if tri else xb, contacts), positions))
    return out
