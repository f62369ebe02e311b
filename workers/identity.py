"""Cluster identity: graph certificates (nauty) and geometric comparison.

Two clusters are *the same cluster* when their contact graphs are isomorphic
and, for some isomorphism between them, their sphere centres agree within
``tol_d`` after an optimal rigid alignment that may include a reflection
(Holmes-Cerfon, SIAM Review 2016: mirror images count as one cluster).

Everything here is a pure function of :class:`~packings.workers.cluster.Cluster`
objects; :class:`ClusterIndex` is a small in-memory store built on top.

pynauty conventions (checked empirically with pynauty 2.8.8.1, see the tests):

* ``pynauty.canon_label(g)`` returns a list ``c`` such that canonical vertex
  ``k`` is original vertex ``c[k]``; i.e. ``A[np.ix_(c, c)]`` is the canonical
  adjacency matrix and ``coords[c]`` lists the spheres in canonical order.
* ``pynauty.certificate(g)`` is that canonical adjacency matrix packed as
  ``n`` rows of nauty setwords (bit ``j`` of row ``k`` set iff canonical
  vertices ``k`` and ``j`` touch), each setword stored in the machine's native
  byte order (little-endian on x86-64).  Certificates are therefore only
  comparable between machines with the same word size and endianness.
* ``pynauty.autgrp(g)[0]`` is a list of generators ``g`` with ``g[i]`` the
  image of vertex ``i``.
"""

from __future__ import annotations

import functools
import weakref
from dataclasses import dataclass
from typing import Iterable, Iterator

import numpy as np
import pynauty

from packings.workers import kernels
from packings.workers.cluster import Cluster, pair_distances

__all__ = [
    "certificate",
    "certificate_hex",
    "graph_certificate",
    "edges_certificate",
    "adjacency_certificate",
    "certificate_key",
    "canonical_labelling",
    "automorphisms",
    "same_geometry",
    "geometry_distance",
    "find_match",
    "alignment",
    "embedding_position",
    "ClusterIndex",
]


# --------------------------------------------------------------------------- graphs


class _Graph(pynauty.Graph):
    """An undirected, uncoloured pynauty graph made from adjacency lists already known to be valid
    (distinct neighbours, each in range: a cluster's contacts).  pynauty's own constructor checks
    every vertex and copies every list in Python, which costs about as much as nauty's labelling of
    a contact graph itself; nauty reads the same four attributes either way (the tests compare both)."""

    def __init__(self, n: int, adjacency: dict[int, list[int]]) -> None:  # no Graph.__init__: no checks
        self.number_of_vertices = n
        self.directed = False
        self._adjacency_dict = adjacency
        self._vertex_coloring = []


def _nauty_graph(cluster: Cluster) -> pynauty.Graph:
    """The contact graph of ``cluster`` as an undirected pynauty graph."""
    return _contact_graph(cluster.n, cluster.contacts)


def _contact_graph(n: int, edges: Iterable[tuple[int, int]]) -> pynauty.Graph:
    """The graph on n vertices with these edges (distinct pairs i < j) for pynauty."""
    adjacency: dict[int, list[int]] = {i: [] for i in range(n)}
    for i, j in edges:
        adjacency[i].append(j)
    return _Graph(n, adjacency)


def certificate(cluster: Cluster) -> bytes:
    """nauty certificate of the contact graph.

    Two clusters with the same number of spheres have equal certificates iff
    their contact graphs are isomorphic (same adjacency matrix up to a
    relabelling of the spheres).  The bytes are the canonical adjacency matrix
    packed by nauty (see the module docstring for the layout).  Computed with
    the rest of the cluster's canonical form, once per cluster.
    """
    return _canonical(cluster).cert


def graph_certificate(cluster: Cluster) -> bytes:
    """:func:`certificate` alone, one call of nauty, nothing else computed or kept: for filters that see
    many clusters once (catalysis)."""
    return edges_certificate(cluster.n, cluster.contacts)


def edges_certificate(n: int, edges: Iterable[tuple[int, int]]) -> bytes:
    """:func:`graph_certificate` of the graph on n vertices with these edges (distinct pairs i < j)."""
    return pynauty.certificate(_contact_graph(n, edges))


def adjacency_certificate(n: int, above: list[list[int]]) -> bytes:
    """:func:`edges_certificate` of the graph on n vertices whose vertex i is joined to each of ``above[i]``
    (distinct vertices, each larger than i)."""
    return pynauty.certificate(_Graph(n, dict(enumerate(above))))


def certificate_hex(cluster: Cluster) -> str:
    """``certificate(cluster)`` as a lowercase hex string (no prefix)."""
    return certificate(cluster).hex()


def certificate_key(cluster: Cluster) -> str:
    """A portable form of the certificate: the same on every machine.

    The upper triangle of the canonical adjacency matrix, read row by row
    (pairs (0,1), (0,2), ..., (1,2), ...), as bits packed most significant
    first and written in lowercase hex.  Equal keys for clusters with the same
    number of spheres iff their certificates are equal; unlike the raw nauty
    certificate it does not depend on the machine's word size or byte order,
    so it is what the database stores.
    """
    c = _canonical(cluster)
    key = _KEYS.get((c.n, c.cert))
    if key is None:
        key = _keep(_KEYS, (c.n, c.cert), np.packbits(c.adjacency[_upper(c.n)]).tobytes().hex())
    return key


#: certificate_key by certificate (the key is a function of the canonical graph, which the certificate
#: determines): a write-back keys a few dozen endpoints of a few contact graphs
_KEYS: dict[tuple[int, bytes], str] = {}


def canonical_labelling(cluster: Cluster) -> np.ndarray:
    """Permutation ``p`` (int64 array) putting the spheres in canonical order.

    Canonical sphere ``k`` is original sphere ``p[k]``: ``coords[p]`` are the
    canonically ordered centres and ``adjacency()[np.ix_(p, p)]`` is the
    canonical adjacency matrix, identical for all clusters with isomorphic
    contact graphs.
    """
    return np.asarray(pynauty.canon_label(_nauty_graph(cluster)), dtype=np.int64)


def _canonical_adjacency(cluster: Cluster, p: np.ndarray) -> np.ndarray:
    """Adjacency matrix of ``cluster`` with spheres in the order ``p``."""
    q = np.empty_like(p)
    q[p] = np.arange(p.size)  # the new place of each sphere
    e = q[cluster.edges()]
    a = np.zeros((cluster.n, cluster.n), dtype=bool)
    a[e[:, 0], e[:, 1]] = True
    a[e[:, 1], e[:, 0]] = True
    return a


def _group_closure(generators: list[np.ndarray], n: int) -> list[np.ndarray]:
    """All elements of the permutation group generated by ``generators``.

    Permutations are arrays ``s`` with ``s[i]`` the image of ``i``; the
    identity comes first.
    """
    identity = np.arange(n, dtype=np.int64)
    seen = {identity.tobytes()}
    group = [identity]
    queue = [identity]
    while queue:
        s = queue.pop()
        for g in generators:
            t = s[g]  # composition s o g
            key = t.tobytes()
            if key not in seen:
                seen.add(key)
                group.append(t)
                queue.append(t)
    return group


#: automorphism groups by certificate (the canonical adjacency matrix): every cluster with that
#: contact graph has the same group, and a worker compares many endpoints with each graph
_GROUPS: dict[tuple[int, bytes], np.ndarray] = {}
_GROUPS_MAX = 65536  #: a cache by certificate is emptied when it reaches this many graphs


def _keep(cache: dict, key, value):
    """``cache[key] = value`` in a cache by certificate, emptied first if it holds _GROUPS_MAX; returns value."""
    if len(cache) >= _GROUPS_MAX:
        cache.clear()
    cache[key] = value
    return value


def _group(c: "_Canonical") -> np.ndarray:
    """The automorphism group of ``c``'s canonical contact graph, one permutation a row, the identity
    first (cached by certificate; the array returned is shared and read-only)."""
    key = (c.n, c.cert)
    group = _GROUPS.get(key)
    if group is None:
        group = np.array(_compute_automorphisms(c.adjacency), dtype=np.int64).reshape(-1, c.n)
        group.setflags(write=False)
        _keep(_GROUPS, key, group)
    return group


def _compute_automorphisms(a: np.ndarray) -> list[np.ndarray]:
    n = a.shape[0]
    g = pynauty.Graph(n, directed=False, adjacency_dict={i: [int(j) for j in np.flatnonzero(a[i])] for i in range(n)})
    generators = [np.asarray(s, dtype=np.int64) for s in pynauty.autgrp(g)[0]]
    return _group_closure(generators, n)


def automorphisms(cluster: Cluster) -> list[np.ndarray]:
    """Every automorphism of the canonically relabelled contact graph.

    Returns the whole group (identity first) as int64 arrays ``s`` with
    ``A[np.ix_(s, s)] == A`` for the canonical adjacency matrix ``A``.  The
    group is the same for every cluster with the same certificate.  It is
    generated by closure from the generators of ``pynauty.autgrp``, so it is
    meant for the small groups that occur for sphere clusters.
    """
    return [s.copy() for s in _group(_canonical(cluster))]


# --------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class _Canonical:
    """A cluster's canonical data, computed once for repeated comparisons."""

    n: int
    cert: bytes
    adjacency: np.ndarray  #: canonical adjacency matrix
    labelling: np.ndarray  #: canonical sphere k is the cluster's sphere labelling[k] (canonical_labelling)
    x: np.ndarray  #: centred coordinates in canonical order
    dist: np.ndarray  #: pair-distance matrix in canonical order
    sorted_dist: np.ndarray  #: sorted upper-triangle pair distances


#: _canonical's results, kept as long as their (immutable) cluster lives: a cluster compared several
#: times (deduplicated within an expansion, then matched against the database) is labelled once
_CANONICAL: "weakref.WeakKeyDictionary[Cluster, _Canonical]" = weakref.WeakKeyDictionary()


def _canonical(cluster: Cluster) -> _Canonical:
    """Certificate, canonical adjacency and canonically ordered, centred geometry (cached per cluster)."""
    c = _CANONICAL.get(cluster)
    if c is None:
        c = _CANONICAL[cluster] = _compute_canonical(cluster)
    return c


def forget_canonical(cluster: Cluster) -> None:
    """Drop what :func:`_canonical` keeps for ``cluster`` (about 3 kB), for a cluster that lives on but
    will not be compared again (an expansion's endpoints that repeat an earlier one)."""
    _CANONICAL.pop(cluster, None)


def _compute_canonical(cluster: Cluster) -> _Canonical:
    g = _nauty_graph(cluster)
    p = np.asarray(pynauty.canon_label(g), dtype=np.int64)
    x = cluster.coords[p]
    x = x - x.mean(axis=0)
    d = pair_distances(x)
    return _Canonical(
        n=cluster.n,
        cert=pynauty.certificate(g),
        adjacency=_canonical_adjacency(cluster, p),
        labelling=p,
        x=x,
        dist=d,
        sorted_dist=np.sort(d[_upper(cluster.n)]),
    )


@functools.lru_cache(maxsize=None)
def _upper(n: int) -> tuple[np.ndarray, np.ndarray]:
    """np.triu_indices(n, 1), once per n."""
    return np.triu_indices(n, 1)


def _same_geometry_canonical(a: _Canonical, b: _Canonical, autos: np.ndarray, tol_d: float) -> bool:
    """same_geometry on precomputed canonical data; ``autos`` is the
    automorphism group of the (shared) canonical graph, one permutation a row."""
    if a.n != b.n or a.cert != b.cert:
        return False
    if a.n == 0:
        return True
    # Coordinates within tol_d move each distance by at most 2*sqrt(3)*tol_d, and sorting does not
    # increase the max difference: a safe cheap rejection on the sorted distances, then the same for
    # each automorphism s (b's distances relabelled by s), then the alignment; all in one kernel call.
    bound = 4.0 * tol_d
    return kernels.some_automorphism_aligns(a.x, b.x, a.dist, b.dist, a.sorted_dist, b.sorted_dist, autos, bound, tol_d)


def same_geometry(a: Cluster, b: Cluster, tol_d: float) -> bool:
    """Whether ``a`` and ``b`` are the same cluster.

    False unless they have the same certificate.  Otherwise both are put in
    canonical order and, for each automorphism ``s`` of the canonical graph,
    canonical sphere ``k`` of ``a`` is matched with canonical sphere ``s[k]``
    of ``b``; after centring both and applying the orthogonal Procrustes
    rotation (reflections allowed), they are the same iff every coordinate
    agrees within ``tol_d``.
    """
    ca, cb = _canonical(a), _canonical(b)
    if ca.n != cb.n or ca.cert != cb.cert:
        return False
    return _same_geometry_canonical(ca, cb, _group(ca), tol_d)


def geometry_distance(a: Cluster, b: Cluster) -> float:
    """How far apart two clusters with one contact graph are: the number :func:`same_geometry` compares
    with ``tol_d``.

    Both in canonical order and centred; for each automorphism ``s`` of the
    canonical graph, the largest coordinate difference between ``a`` and
    ``b``'s spheres relabelled by ``s`` after the optimal orthogonal alignment
    (reflections allowed, :func:`kernels.aligned_max_error`); the smallest over
    ``s``.  So ``same_geometry(a, b, tol_d)`` iff ``geometry_distance(a, b) <=
    tol_d``.  It is ``a`` that is rotated onto ``b``, and the largest
    coordinate difference depends on the frame, so the distance is not quite
    symmetric (as ``same_geometry`` is not): the store compares a new endpoint
    with the stored clusters, ``find_match(new, stored)``.  Used to audit a
    catalogue for copies of one cluster stored as two.  Raises ValueError if
    the certificates differ (no correspondence of spheres to measure).
    """
    ca, cb = _canonical(a), _canonical(b)
    if ca.n != cb.n or ca.cert != cb.cert:
        raise ValueError("geometry_distance needs two clusters with the same contact graph (certificate)")
    if ca.n == 0:
        return 0.0
    return min(kernels.aligned_max_error(ca.x, cb.x[s]) for s in _group(ca))


def find_match(cluster: Cluster, candidates: Iterable[Cluster], tol_d: float) -> int | None:
    """Index of the first candidate that is the same cluster (same certificate
    and same geometry within ``tol_d``, see :func:`same_geometry`), else None."""
    c = _canonical(cluster)
    autos: np.ndarray | None = None
    for idx, other in enumerate(candidates):
        o = _canonical(other)
        if o.n != c.n or o.cert != c.cert:
            continue
        if autos is None:
            autos = _group(c)
        if _same_geometry_canonical(c, o, autos, tol_d):
            return idx
    return None


def alignment(a: Cluster, b: Cluster, tol_d: float, same: bool = False) -> np.ndarray | None:
    """The relabelling that makes ``a`` the cluster ``b``: ``t`` (int64) with sphere ``i`` of ``a`` at
    sphere ``t[i]`` of ``b`` once aligned, by the rule of :func:`same_geometry`; None if they are not the
    same cluster.  Where ``b`` has symmetries several relabellings do; this is the first automorphism
    of the canonical graph (in the group's order) that aligns.  With ``same`` (the caller knows them to be
    the same cluster, e.g. from :func:`find_match`) and a contact graph with no automorphism but the
    identity, the canonical labellings alone give it, with no alignment."""
    ca, cb = _canonical(a), _canonical(b)
    if ca.n != cb.n or ca.cert != cb.cert:
        return None
    autos = _group(ca)
    if same and len(autos) == 1:
        return _relabelling(ca, cb, autos[0])
    return next(_aligning(ca, cb, autos, tol_d), None)


def _relabelling(a: _Canonical, b: _Canonical, s: np.ndarray) -> np.ndarray:
    """``t``, sphere ``i`` of ``a`` being sphere ``t[i]`` of ``b``, when canonical ``k`` of ``a`` is
    canonical ``s[k]`` of ``b``."""
    t = np.empty(a.n, dtype=np.int64)
    t[a.labelling] = b.labelling[s]
    return t


def _aligning(a: _Canonical, b: _Canonical, autos: np.ndarray, tol_d: float) -> Iterator[np.ndarray]:
    """The relabellings (:func:`_relabelling`) by the automorphisms ``autos`` of the canonical graph, in
    their order, under which ``a`` is ``b`` by the rule of :func:`same_geometry`: the cheap rejection
    (distances within 4 tol_d), then the alignment."""
    relabelled = b.dist[autos[:, :, None], autos[:, None, :]]
    near = np.abs(relabelled - a.dist).max(axis=(1, 2), initial=0.0) <= 4.0 * tol_d
    for s, ok in zip(autos, near):
        if ok and kernels.aligned_max_error(a.x, b.x[s]) <= tol_d:
            yield _relabelling(a, b, s)


def symmetries(cluster: Cluster, tol_d: float) -> np.ndarray:
    """The permutations of the spheres that are symmetries of ``cluster``, one a row, the identity first.

    A row ``t`` is an automorphism of the contact graph, in the cluster's own labels, that is also an
    isometry: after the optimal orthogonal alignment (reflections allowed), sphere ``i`` of the
    cluster lies within ``tol_d`` of where sphere ``t[i]`` is, in every coordinate (the rule of
    :func:`same_geometry`: the cluster is the same cluster as itself relabelled by ``t``).  They form
    a group: the graph automorphisms that move the geometry are left out.  Breaking contacts B of a
    cluster and breaking their image under ``t`` start congruent paths
    (:func:`packings.workers.expand.expand` follows one path of each such set, see docs/method.md).
    """
    c = _canonical(cluster)
    group = _group(c)
    if len(group) == 1 or c.n == 0:
        return np.arange(c.n, dtype=np.int64)[None, :]
    return np.array(list(_aligning(c, c, group, tol_d)), dtype=np.int64).reshape(-1, c.n)


# --------------------------------------------------------------------------- embedding order


def _precedes(a: _Canonical, b: _Canonical, resolution: float) -> bool:
    """Whether geometry ``a`` comes before ``b`` in embedding order: their pair distances sorted from
    the largest down, compared one by one, the first that differs by more than ``resolution``
    decides, and the smaller comes first (the more compact geometry)."""
    differ = np.flatnonzero(np.abs(a.sorted_dist - b.sorted_dist) > resolution)
    if differ.size == 0:
        return False
    k = differ[-1]  # sorted_dist is ascending: its last differing entry is the largest one
    return bool(a.sorted_dist[k] < b.sorted_dist[k])


def embedding_position(cluster: Cluster, others: Iterable[Cluster], tol_d: float) -> int:
    """Where a new geometry of a contact graph goes among ``others``, the stored geometries of that
    graph in embedding order: the index of the first one it precedes, else the end.

    Embedding numbers are a function of geometry, not of the order in which clusters were found, so
    that two runs give every (certificate, embedding) key the same geometry.  The order is by the pair
    distances sorted from the largest down, compared with a resolution of ``4 tol_d``: two copies of
    one cluster (coordinates within ``tol_d`` after alignment) have sorted distances within about
    ``3.5 tol_d`` (:func:`same_geometry`'s first rejection), so they never compare unequal, and the
    largest distance, the cluster's diameter, decides between distinct geometries in practice.  Two
    distinct geometries whose sorted distances agree within the resolution keep the order in which
    they were found (see docs/method.md)."""
    c = _canonical(cluster)
    resolution = 4.0 * tol_d
    k = 0
    for other in others:
        if _precedes(c, _canonical(other), resolution):
            break
        k += 1
    return k


# --------------------------------------------------------------------------- index


class ClusterIndex:
    """In-memory set of distinct clusters, deduplicated by certificate then geometry.

    Ids are 0, 1, 2, ... in insertion order.  Clusters with the same contact
    graph but different geometry are different *embeddings* of that graph,
    numbered 0, 1, ... in embedding order (:func:`embedding_position`), as the
    database numbers them.
    """

    def __init__(self) -> None:
        self._clusters: list[Cluster] = []
        self._canon: list[_Canonical] = []
        self._by_cert: dict[tuple[int, bytes], list[int]] = {}  #: ids of each graph, in embedding order

    def add(self, cluster: Cluster, tol_d: float) -> tuple[int, bool]:
        """Insert ``cluster`` unless an equal one is stored; return ``(id, is_new)``."""
        c = _canonical(cluster)
        key = (c.n, c.cert)
        ids = self._by_cert.setdefault(key, [])
        if ids:
            autos = _group(c)
            for i in ids:
                if _same_geometry_canonical(self._canon[i], c, autos, tol_d):
                    return i, False
        new_id = len(self._clusters)
        ids.insert(embedding_position(cluster, (self._clusters[i] for i in ids), tol_d), new_id)
        self._clusters.append(cluster)
        self._canon.append(c)
        return new_id, True

    def embedding_number(self, id: int) -> int:
        """The cluster's embedding number among the clusters with its contact graph (0, 1, ...)."""
        c = self._canon[id]
        return self._by_cert[(c.n, c.cert)].index(id)

    def __len__(self) -> int:
        return len(self._clusters)

    def __getitem__(self, id: int) -> Cluster:
        return self._clusters[id]

    def __iter__(self) -> Iterator[Cluster]:
        return iter(self._clusters)
