"""Catalysis: rigid clusters of n spheres found by deleting spheres from rigid clusters of n + k.

Pure numpy; no database or Dask imports.

Why.  The path enumeration (docs/method.md) finds every rigid cluster connected to its seed
by one-dimensional paths.  Some clusters are reached by none: at n = 11 a fragment of an hcp
lattice missing one contact (26 contacts), which Holmes-Cerfon (SIAM Review 2016) found by
deleting a sphere from a cluster of 12.  Deleting spheres from every stored cluster of
n + k spheres and keeping the remainders that are rigid seeds such clusters.

Method.  For a rigid parent of N + k spheres (stored clusters are projected and polished:
their contacts hold to the Newton tolerance) and every set D of k spheres:

1. the remainder is the parent's coordinates without the spheres of D, its spheres renumbered
   0..N-1 in the parent's order, and its contacts the parent's contacts between kept spheres,
   renumbered (sorted pairs i < j, as everywhere);
2. a remainder with a sphere of fewer than three contacts is not rigid (the sphere turns about
   the line through its at most two neighbours, an exact motion) and is not tested further
   (``few-contacts``; the rigidity test says the same, only slower: this is checked first, as
   most remainders end here);
3. a remainder whose contacts hold no triangle is skipped (nothing to pin: ``no-triangle``);
4. otherwise the endpoint rule of a path decides (docs/method.md): pairs within
   tol_a0 of touching that close to a rigid cluster within tol_a0 make the remainder that cluster
   (:func:`packings.workers.paths.resolve_near_pairs`), else the remainder is kept when the rigidity test
   with its isolation probe calls it rigid (:func:`packings.workers.paths.endpoint_rigidity`); and only
   with at least ``params.min_contacts`` contacts if that is set.

Moving one sphere (:func:`moved_remainders`).  Catalysis from n + 1 needs the catalogue of n + 1, which
is out of reach for the largest n run.  Its parents can be made instead: glue a sphere onto a contact
triangle of a stored cluster of n, on either side of it (where it overlaps no sphere), and delete
each of the cluster's own spheres: one sphere moved to another place.  At n = 11 this finds the
cluster no path reaches from the path clusters of 11 alone (docs/method.md).  Nearly all of these
remainders are floppy, with independent contacts: the compiled kernels certify them first, a glued
cluster's at a time, where nothing else could decide otherwise (:func:`_floppy`), with the verdict
:func:`remainder` would give.  Of the others most are stored clusters again, and one glued cluster
repeats many others: such a remainder is decided only when its contact graph and sorted pair distances
match no cluster seen before (stored, or decided earlier in the same pass: :class:`Seen`).

The remainder's coordinates are not projected again: deleting spheres deletes equations, so
the parent's point still solves the remainder's.  Its contacts, measured again from the
coordinates with :func:`packings.workers.cluster.contacts_from_coords` (``params.tol_a``), must be the
inherited ones; they always are (pair distances do not change when other spheres are
deleted), and a remainder where they differ is rejected (``contacts-differ``) rather than
stored with contacts its geometry does not have.
"""

from __future__ import annotations

import functools
import hashlib
import threading
from dataclasses import dataclass
from itertools import combinations
from math import comb
from typing import Iterator

import numpy as np

from packings.workers import kernels
from packings.workers.cluster import Cluster, contacts_from_coords, pair, pair_distances, triangles
from packings.workers.identity import adjacency_certificate, graph_certificate
from packings.workers.outcomes import BELOW_MIN_CONTACTS, NO_TRIANGLE, RIGID
from packings.workers.params import Params
from packings.workers.paths import endpoint_rigidity, resolve_near_pairs
from packings.workers.rigidity import Rigidity, contact_triangle, rigidity_without_stress
from packings.workers.seeds import cap_positions

NOT_RIGID = "not-rigid"  #: the rigidity test says floppy or undecided
FEW_CONTACTS = "few-contacts"  #: a sphere of the remainder has fewer than three contacts: not rigid
CONTACTS_DIFFER = "contacts-differ"  #: the contacts measured from the coordinates are not the inherited ones


@dataclass(frozen=True)
class Remainder:
    """What is left of a parent after deleting the spheres ``deleted`` (the parent's indices).

    ``kept[i]`` is the parent's index of the remainder's sphere ``i``.  ``rigidity`` is set when
    the rigidity test ran (outcomes ``rigid``, ``not-rigid``, ``below-min-contacts``).
    """

    deleted: tuple[int, ...]
    kept: tuple[int, ...]
    cluster: Cluster
    outcome: str
    rigidity: Rigidity | None = None

    @property
    def rigid(self) -> bool:
        return self.outcome == RIGID


def sub_cluster(parent: Cluster, kept) -> Cluster:
    """The spheres ``kept`` of ``parent`` (in that order, renumbered 0..) with the parent's contacts among them."""
    kept = tuple(int(i) for i in kept)
    new = {p: q for q, p in enumerate(kept)}
    # the shared pairs (cluster.pair), so that contacts kept in order need no sorting by Cluster
    contacts = tuple(pair(new[i], new[j]) for i, j in parent.contacts if i in new and j in new)
    return Cluster(parent.coords[list(kept)], contacts)


def _without_sphere(parent: Cluster, s: int) -> Cluster:
    """``sub_cluster`` of every sphere of ``parent`` but s, in order: the contacts renumbered stay sorted."""
    return Cluster.of_normal(
        np.concatenate((parent.coords[:s], parent.coords[s + 1 :])),
        tuple(pair(i - (i > s), j - (j > s)) for i, j in parent.contacts if i != s and j != s),
    )


def remainder(parent: Cluster, deleted, params: Params) -> Remainder:
    """Delete the spheres ``deleted`` from ``parent`` and decide the rest (module doc, steps 1-4)."""
    deleted = tuple(sorted(int(i) for i in deleted))
    gone = set(deleted)
    kept = tuple(i for i in range(parent.n) if i not in gone)
    c = sub_cluster(parent, kept)
    if np.bincount(c.edges().ravel(), minlength=c.n).min() < 3:
        return Remainder(deleted, kept, c, FEW_CONTACTS)
    tri = contact_triangle(c.contacts)
    if tri is None:
        return Remainder(deleted, kept, c, NO_TRIANGLE)
    if contacts_from_coords(c.coords, params.tol_a) != c.contacts:
        return Remainder(deleted, kept, c, CONTACTS_DIFFER)
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(c.n, tri)
    resolved = resolve_near_pairs(x, c.contacts, free, params)
    if resolved is not None:  # pairs within tol_a0 close to a rigid cluster: that is the remainder
        c = Cluster(resolved[0].reshape(-1, 3), resolved[1])
        rig = resolved[2]
    else:
        rig = endpoint_rigidity(x, c.contacts, free, params)
    if not rig.rigid:
        return Remainder(deleted, kept, c, NOT_RIGID, rig)
    if params.min_contacts is not None and c.m < params.min_contacts:
        return Remainder(deleted, kept, c, BELOW_MIN_CONTACTS, rig)
    return Remainder(deleted, kept, c, RIGID, rig)


def remainders(parent: Cluster, k: int, params: Params) -> Iterator[Remainder]:
    """Every remainder of ``parent`` with ``k`` spheres deleted, rigid or not, in lexicographic order of
    the deleted sets (``comb(parent.n, k)`` of them)."""
    if not 1 <= k <= parent.n - 3:
        raise ValueError(f"can delete 1 to {parent.n - 3} of {parent.n} spheres, not {k}")
    for deleted in combinations(range(parent.n), k):
        yield remainder(parent, deleted, params)


def rigid_remainders(parent: Cluster, k: int, params: Params) -> list[Remainder]:
    """The remainders of ``parent`` with ``k`` spheres deleted that pass the endpoint rule (rigid, and
    at least ``params.min_contacts`` contacts if set)."""
    return [r for r in remainders(parent, k, params) if r.rigid]


def remainder_count(n: int, k: int) -> int:
    """How many remainders a parent of n spheres has with k deleted."""
    return comb(n, k)


def glued(cluster: Cluster, params: Params) -> Iterator[tuple[tuple[int, int, int], Cluster]]:
    """Every cluster of n + 1 spheres made by putting a sphere (number n) on a contact triangle of ``cluster``,
    on either side of it, where no centre is closer to it than 1 - tol_a (an overlap); its contacts are
    measured (closer than 1 + tol_a).  With the triangle, in the order of :func:`packings.workers.cluster.triangles`."""
    x = cluster.coords
    for tri in triangles(cluster.contacts):
        for q in cap_positions(x, tri):
            d = np.sqrt(((x - q) ** 2).sum(axis=1))
            if np.any(d < 1.0 - params.tol_a):
                continue
            new = tuple(pair(int(i), cluster.n) for i in np.flatnonzero(d < 1.0 + params.tol_a))
            yield tri, Cluster.of_normal(np.vstack([x, q]), tuple(sorted(cluster.contacts + new)))


#: digests placed together when the record's table grows (:meth:`Seen._grow`): the work arrays stay a few MiB
GROW_CHUNK = 1 << 16


class Seen:
    """Clusters already decided, by contact graph (nauty certificate) and sorted pair distances.

    ``cluster in seen`` when a cluster with the same contact graph was added whose sorted pair distances
    fall in the same cells of a grid of side ``4 tol_d``: each distance rounded to the nearest multiple of
    ``4 tol_d``, the same.  Then every distance is within ``4 tol_d`` of the other's, what
    :func:`packings.workers.identity.same_geometry` requires before it aligns, so the record calls seen no
    cluster that a comparison of the distances within that bound would call new.  It is a filter for work,
    not the identity: it only chooses which remainders are not decided again, and what is stored is matched
    by the identity as always.  A copy whose distances straddle a cell's wall is decided again (work, not a
    loss); repeats of one remainder agree far closer than a cell (docs/method.md).

    A pass at n = 13 keeps millions of them, so a cluster is kept as one 128-bit digest (blake2b) of its
    certificate and its rounded distances, in an open-addressing table of numpy arrays: 16 bytes a slot,
    the table at most half full.  Two different clusters share a digest with a chance of about 2^-128 a
    pair.
    """

    def __init__(self, tol_d: float):
        self.bound = 4.0 * tol_d
        self._keys = np.zeros((1 << 10, 2), np.uint64)  #: digests, two words each (0, 0: an empty slot)
        self._count = 0
        self._lock = threading.Lock()  # a worker's threads share one record (packings.service.catalysis)

    def add(self, cluster: Cluster) -> bool:
        """Remember ``cluster``; False if it was seen already."""
        d = pair_distances(cluster.coords)[_upper(cluster.n)]
        return self.add_parts(graph_certificate(cluster), np.sort(d))

    def add_parts(self, certificate: bytes, sorted_distances: np.ndarray) -> bool:
        """:meth:`add` for a cluster given by its graph certificate and sorted pair distances."""
        return self.add_cells(certificate, self.cells(sorted_distances))

    def cells(self, sorted_distances: np.ndarray) -> np.ndarray:
        """The cells of the grid that sorted pair distances fall in (each row of a 2-d array one cluster's)."""
        return np.rint(np.asarray(sorted_distances, np.float64) / self.bound).astype(np.int64)

    def add_cells(self, certificate: bytes, cells: np.ndarray) -> bool:
        """:meth:`add_parts` for a cluster given by its graph certificate and the :meth:`cells` of its distances."""
        h = hashlib.blake2b(certificate, digest_size=16)
        h.update(cells.tobytes())
        b = h.digest()
        lo, hi = int.from_bytes(b[:8], "little"), int.from_bytes(b[8:], "little")
        if lo == 0 and hi == 0:
            lo = 1
        with self._lock:
            return self._add(lo, hi)

    def _add(self, lo: int, hi: int) -> bool:
        """:meth:`add_parts` for the digest (``lo``, ``hi``), under the lock."""
        slot = self._slot(lo, hi)
        if int(self._keys[slot, 0]) != 0 or int(self._keys[slot, 1]) != 0:
            return False
        if 2 * (self._count + 1) > len(self._keys):
            self._grow()
            slot = self._slot(lo, hi)
        self._keys[slot] = (lo, hi)
        self._count += 1
        return True

    def _slot(self, lo: int, hi: int) -> int:
        """The slot of the digest in the table, or the empty slot where it would go (linear probing)."""
        mask = len(self._keys) - 1
        i = lo & mask
        while True:
            a, b = int(self._keys[i, 0]), int(self._keys[i, 1])
            if (a == lo and b == hi) or (a == 0 and b == 0):
                return i
            i = (i + 1) & mask

    def _grow(self) -> None:
        """The table twice as large, every digest in it again.

        The digests are placed in rounds, a chunk at a time, in numpy arrays (as a list of Python ints they
        would take about ten times the table's own bytes, and a Python loop over millions of them would hold
        the lock for seconds): each round, the first digest bound for each empty slot takes it and the
        others probe the next slot.  Without deletions any order of insertion leaves every digest reachable
        from its home slot through occupied slots, which is all that :meth:`_slot` needs."""
        live = self._keys[(self._keys[:, 0] != 0) | (self._keys[:, 1] != 0)]
        self._keys = table = np.zeros((2 * len(self._keys), 2), np.uint64)
        mask = np.uint64(len(table) - 1)
        for start in range(0, len(live), GROW_CHUNK):
            keys = live[start : start + GROW_CHUNK]
            pos = keys[:, 0] & mask
            while keys.size:
                free = np.flatnonzero((table[pos, 0] == 0) & (table[pos, 1] == 0))
                _, first = np.unique(pos[free], return_index=True)
                placed = free[first]
                table[pos[placed]] = keys[placed]
                left = np.ones(len(keys), bool)
                left[placed] = False
                keys, pos = keys[left], (pos[left] + np.uint64(1)) & mask

    def __len__(self) -> int:
        return self._count


@functools.lru_cache(maxsize=None)
def _upper(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.triu_indices(n, 1)


@functools.lru_cache(maxsize=None)
def _without(n: int, s: int) -> tuple[np.ndarray, np.ndarray]:
    """The upper-triangle pairs of n spheres that do not involve sphere s, as indices into the n x n matrix."""
    i, j = _upper(n)
    keep = (i != s) & (j != s)
    return i[keep], j[keep]


@functools.lru_cache(maxsize=None)
def _without_each(n: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_without` of every sphere s of n, as row s of two (n x (n - 1)(n - 2)/2) index arrays."""
    out = [_without(n, s) for s in range(n)]
    rows, cols = np.stack([i for i, _ in out]), np.stack([j for _, j in out])
    rows.setflags(write=False)
    cols.setflags(write=False)
    return rows, cols


@dataclass(frozen=True)
class Moved:
    """Sphere ``sphere`` of a cluster put on the contact triangle ``triangle`` (on its ``side``, 0 or 1, as
    :func:`packings.workers.seeds.cap_positions` orders them).  ``remainder`` is the remainder decided; None
    when it was certified floppy from the glued cluster alone (``floppy``: its flexes; the remainder is not
    built, :meth:`built` builds it) or was seen (``floppy`` 0)."""

    sphere: int
    triangle: tuple[int, int, int]
    side: int
    remainder: Remainder | None
    floppy: int = 0

    @property
    def seen(self) -> bool:
        """Not decided: a cluster in the record of those seen has its graph and distances."""
        return self.remainder is None and self.floppy == 0

    def built(self, parent: Cluster) -> Remainder | None:
        """The remainder as :func:`remainder` gives it (``parent``: the glued cluster), built for one certified
        floppy; None for one seen."""
        if self.remainder is not None or self.floppy == 0:
            return self.remainder
        s, n = self.sphere, parent.n
        return Remainder(
            (s,),
            tuple(i for i in range(n) if i != s),
            _without_sphere(parent, s),
            NOT_RIGID,
            rigidity_without_stress(self.floppy),
        )


def moved_remainders(cluster: Cluster, params: Params, seen: Seen) -> Iterator[Moved]:
    """Each sphere of ``cluster`` moved onto each contact triangle (module doc): for every glued cluster
    (:func:`glued`) and every sphere s of ``cluster`` whose removal leaves every sphere three contacts,
    the remainder without s.  The remainder's spheres are the cluster's without s, in order, then the
    moved one.

    Nearly every remainder is floppy: its contacts are independent and fewer than its free coordinates.
    The compiled kernels certify that for all of a glued cluster's remainders at once, where nothing else
    could decide otherwise (:func:`_floppy`), with the verdict :func:`remainder` gives; those are neither
    built nor looked up in ``seen`` (``Moved.floppy``: no stored cluster nor rigid remainder can be one,
    docs/method.md).  Each other remainder is decided by :func:`remainder` unless it is in ``seen``, and
    added to ``seen``."""
    sides: dict[tuple[int, int, int], int] = {}
    measured = contacts_from_coords(cluster.coords, params.tol_a) == cluster.contacts  # as _floppy needs
    for tri, parent in glued(cluster, params):
        side = sides[tri] = sides.get(tri, -1) + 1
        n = parent.n
        edges = parent.edges()
        adjacent = np.zeros((n, n), dtype=bool)
        adjacent[edges[:, 0], edges[:, 1]] = True
        adjacent[edges[:, 1], edges[:, 0]] = True
        degree = adjacent.sum(axis=1)
        # row s: every sphere's contacts once s is deleted (s itself counted as enough)
        left = degree - adjacent[: cluster.n]
        left[np.arange(cluster.n), np.arange(cluster.n)] = 3
        movable = np.flatnonzero(left.min(axis=1) >= 3)  # the others are not rigid (remainder, step 2)
        if not movable.size:
            continue
        d = pair_distances(parent.coords)
        # a remainder with as many contacts as free coordinates or more has no flex the kernels could certify
        fewer = movable[parent.m - degree[movable] < 3 * (n - 1) - 6]
        floppy = _floppy(parent, edges, adjacent, d, params, fewer.tolist()) if measured and fewer.size else {}
        rest = np.array([s for s in movable.tolist() if s not in floppy], dtype=np.int64)
        fresh = dict(zip(rest.tolist(), _add_to_seen(seen, parent, d, rest))) if rest.size else {}
        for s in movable.tolist():
            if s in floppy:
                yield Moved(s, tri, side, None, floppy[s])
            elif not fresh[s]:
                yield Moved(s, tri, side, None)
            else:
                yield Moved(s, tri, side, remainder(parent, (s,), params))


def _add_to_seen(seen: Seen, parent: Cluster, d: np.ndarray, spheres: np.ndarray) -> list[bool]:
    """The remainders of the glued cluster ``parent`` (pair distances ``d``) without each sphere of ``spheres``
    added to ``seen``, their graphs and distances taken from the parent without building them (spheres after
    s move down one); for each, whether it was new."""
    n = parent.n
    above: list[list[int]] = [[] for _ in range(n)]  # each sphere's neighbours with a larger number
    for i, j in parent.contacts:
        above[i].append(j)
    rows, cols = _without_each(n)
    cells = seen.cells(np.sort(d[rows[spheres], cols[spheres]], axis=1))
    out = []
    for q, s in enumerate(spheres.tolist()):
        graph = adjacency_certificate(n - 1, [[j - (j > s) for j in above[i] if j != s] for i in range(n) if i != s])
        out.append(seen.add_cells(graph, cells[q]))
    return out


#: :func:`_floppy` leaves to :func:`remainder` the remainders with a pair that is not a contact within this of
#: 1 + tol_a0 (the distances it measures may differ from those :func:`remainder` measures in the last bits)
NEAR_ROOM = 1e-9


def _floppy(
    parent: Cluster, edges: np.ndarray, adjacent: np.ndarray, d: np.ndarray, params: Params, spheres: list[int]
) -> dict[int, int]:
    """The flexes of those remainders of the glued cluster ``parent`` without one sphere of ``spheres`` that
    :func:`remainder` calls floppy with no self-stress (its contacts certified independent,
    :func:`packings.workers.kernels.regular_flexes`, and fewer than its free coordinates), where that is
    certain from the parent alone; the others are left to :func:`remainder`.  ``edges``, ``adjacent`` and
    ``d``: the parent's contacts, adjacency matrix and pair distances; the parent's contacts between the
    spheres of the cluster it was glued onto are those measured (the caller checks that).

    What :func:`remainder` would check first holds for each: the caller left out the remainders with a sphere
    of fewer than three contacts, and deleting a sphere renumbers the others in order, so the contacts it
    measures between two kept spheres are the parent's measured (:func:`_measured_last` for the glued one),
    and its first contact triangle (:func:`packings.workers.rigidity.contact_triangle`) is the parent's first
    that avoids the sphere, renumbered.  Decided here only where nothing else could decide: no pair that is
    not a contact is within :data:`NEAR_ROOM` of 1 + tol_a0 (else resolve_near_pairs may close it), and
    :func:`packings.workers.kernels.floppy_without` certifies the remainder with room for its own frame's
    rounding."""
    if not _measured_last(parent, params.tol_a):
        return {}
    spheres = np.asarray(spheres, dtype=np.int64)
    near = (d < 1.0 + params.tol_a0 + NEAR_ROOM) & ~adjacent
    np.fill_diagonal(near, False)
    if near.any():  # keep the remainders that lose a sphere of every near pair
        i, j = np.nonzero(np.triu(near))
        spheres = spheres[((i[None, :] == spheres[:, None]) | (j[None, :] == spheres[:, None])).all(axis=1)]
    triangles = first_triangles_without(adjacent, spheres)
    ask = triangles[:, 0] >= 0
    if not ask.any():
        return {}
    spheres, triangles = spheres[ask], triangles[ask]
    triangles -= triangles > spheres[:, None]  # in the remainders' own labels
    flexes = kernels.floppy_without(parent.coords, edges, spheres, triangles, params.tol_n)
    return {s: f for s, f in zip(spheres.tolist(), flexes.tolist()) if f > 0}


def first_triangles_without(adjacent: np.ndarray, spheres: np.ndarray) -> np.ndarray:
    """For each sphere s of ``spheres``: :func:`packings.workers.rigidity.contact_triangle` of the contacts
    (adjacency matrix ``adjacent``) without those of s, as a row (a, b, c) of sphere numbers of the whole;
    (-1, -1, -1) where none is left.  That triangle is the first contact (a, b), a < b, in lexicographic order
    with a common neighbour, c the least of those: the first triangle of all the contacts wherever it avoids s
    (deleting s takes no common neighbour from an earlier contact, which has none)."""
    a = adjacent.astype(np.int64)
    first = _first_triangle(a)
    out = np.tile(first, (len(spheres), 1))
    for q, s in enumerate(np.asarray(spheres).tolist()):
        if s in first:
            left = a.copy()
            left[s, :] = 0
            left[:, s] = 0
            out[q] = _first_triangle(left)
    return out


def _first_triangle(a: np.ndarray) -> tuple[int, int, int]:
    """The first triangle of the contacts of the 0/1 adjacency matrix ``a`` (first_triangles_without)."""
    n = len(a)
    pairs = (a * (a @ a) > 0) & _above_diagonal(n)  # contacts i < j with a common neighbour
    if not pairs.any():
        return -1, -1, -1
    i, j = divmod(int(np.argmax(pairs)), n)
    return i, j, int(np.argmax(a[i] * a[j]))


@functools.lru_cache(maxsize=None)
def _above_diagonal(n: int) -> np.ndarray:
    """The n x n mask of the entries (i, j) with i < j (read-only, shared)."""
    out = np.triu(np.ones((n, n), dtype=bool), 1)
    out.setflags(write=False)
    return out


def _measured_last(parent: Cluster, tol_a: float) -> bool:
    """Whether the contacts of the last sphere of ``parent`` are those :func:`contacts_from_coords` measures:
    its distances to the others computed as it computes them, pair by pair."""
    x = parent.coords
    last = x.shape[0] - 1
    diff = x[:last] - x[last]
    near = np.flatnonzero(np.sqrt(np.einsum("ij,ij->i", diff, diff)) < 1.0 + tol_a)
    return near.tolist() == [i for i, j in parent.contacts if j == last]
