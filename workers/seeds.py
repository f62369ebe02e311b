"""Rigid starting clusters for any n: polytetrahedra built by gluing spheres onto contact triangles, and,
for runs restricted to clusters with many contacts (``--min-contacts``), close-packed fragments: the one
with the most contacts that a beam search over the fcc and hcp lattices finds, or, where that has too
few, the one with the most contacts among every close-packed fragment listed
(:func:`packings.workers.fragments.close_packed`)."""

from __future__ import annotations

import functools

import numpy as np

from packings.workers import kernels
from packings.workers.cluster import Cluster, cross3, triangles
from packings.workers.fragments import close_packed
from packings.workers.params import DEFAULT, Params
from packings.workers.rigidity import rigidity


def cap_positions(p: np.ndarray, tri: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The two points at distance 1 from each sphere of a unit triangle (either side of its plane).

    For a triangle of unit-distance spheres the apex sits above the centroid at
    height sqrt(2/3).
    """
    a, b, c = (p[i] for i in tri)
    centroid = (a + b + c) / 3.0
    normal = cross3(b - a, c - a)
    normal /= np.linalg.norm(normal)
    r2 = np.sum((a - centroid) ** 2)
    height = np.sqrt(max(1.0 - r2, 0.0))
    return centroid + height * normal, centroid - height * normal


def glue_sphere(cluster: Cluster, params: Params = DEFAULT) -> Cluster:
    """A rigid (n+1)-cluster: a new sphere touching a contact triangle of ``cluster``.

    Among all triangles and both sides, the position whose nearest other sphere
    is farthest is chosen (deterministic; it avoids overlaps and accidental
    near-contacts).  Raises ValueError if every position overlaps.
    """
    p = cluster.coords
    best, best_gap = None, -np.inf
    for tri in triangles(cluster.contacts):
        others = np.array([k for k in range(cluster.n) if k not in tri], dtype=np.int64)
        for q in cap_positions(p, tri):
            gap = np.min(np.linalg.norm(p[others] - q, axis=1)) if others.size else np.inf
            if gap > best_gap + 1e-12:
                best, best_gap = q, gap
    if best is None or best_gap < 1.0 + params.tol_a0:
        raise ValueError("no position to glue a sphere without overlap or an extra contact")
    return Cluster.from_coords(np.vstack([p, best]), params)


def tetrahedron() -> Cluster:
    """The regular tetrahedron of unit edge."""
    p = np.array(
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, np.sqrt(3) / 2, 0.0], [0.5, np.sqrt(3) / 6, np.sqrt(2.0 / 3.0)]]
    )
    return Cluster.from_coords(p)


def lattice_sites(kind: str, radius: float = 3.5) -> np.ndarray:
    """The sites of the ``fcc`` or ``hcp`` lattice of unit nearest-neighbour distance within ``radius``
    of the origin, which is a site."""
    r = int(np.ceil(2 * radius)) + 1
    if kind == "fcc":  # the integer points with an even sum, scaled so that neighbours are 1 apart
        g = np.array(
            [
                (i, j, k)
                for i in range(-r, r + 1)
                for j in range(-r, r + 1)
                for k in range(-r, r + 1)
                if (i + j + k) % 2 == 0
            ],
            dtype=float,
        ) / np.sqrt(2.0)
    elif kind == "hcp":  # triangular layers A B A B ..., sqrt(2/3) apart, B over the centres of A's triangles
        a1, a2 = np.array([1.0, 0.0, 0.0]), np.array([0.5, np.sqrt(3) / 2, 0.0])
        shift = (a1 + a2) / 3.0
        g = np.array(
            [
                i * a1 + j * a2 + (shift if layer % 2 else 0.0) + [0.0, 0.0, layer * np.sqrt(2.0 / 3.0)]
                for layer in range(-r, r + 1)
                for i in range(-2 * r, 2 * r + 1)
                for j in range(-2 * r, 2 * r + 1)
            ]
        )
    else:
        raise ValueError(f"unknown lattice {kind!r}: fcc or hcp")
    return g[np.linalg.norm(g, axis=1) <= radius + 1e-9]


def _best_fragments(sites: np.ndarray, n: int, beam: int) -> list[tuple[int, tuple[int, ...]]]:
    """(contacts, site indices) of the n-site fragments with the most contacts a beam search grows from
    the site at the origin, adding a touching site at a time and keeping the ``beam`` best (the most
    contacts, then the most compact) distinct fragments at each size; best first."""
    d = np.linalg.norm(sites[:, None] - sites[None], axis=-1)
    touching = np.abs(d - 1.0) < 1e-9
    origin = int(np.argmin(np.linalg.norm(sites, axis=1)))
    level: dict[tuple[int, ...], int] = {(origin,): 0}
    for _ in range(n - 1):
        grown: dict[tuple[int, ...], int] = {}
        for frag, m in level.items():
            inside = np.zeros(len(sites), dtype=bool)
            inside[list(frag)] = True
            gain = touching[:, inside].sum(axis=1)
            for site in np.flatnonzero((gain > 0) & ~inside):
                key = tuple(sorted((*frag, int(site))))
                grown[key] = m + int(gain[site])

        def spread(frag: tuple[int, ...]) -> float:
            x = sites[list(frag)]
            return float(((x - x.mean(axis=0)) ** 2).sum())

        level = dict(sorted(grown.items(), key=lambda kv: (-kv[1], spread(kv[0]), kv[0]))[:beam])
    return sorted(((m, frag) for frag, m in level.items()), key=lambda t: -t[0])


@functools.lru_cache(maxsize=8)  # a run's start checks it before its Dask cluster starts, then seeds with it
def close_packed_seed(n: int, params: Params = DEFAULT, beam: int = 64) -> Cluster:
    """The rigid close-packed fragment of n spheres (fcc or hcp) with the most contacts found by a beam
    search (:func:`_best_fragments`), in the frame of its first contact triangle.  Not always the one with
    the most contacts: at n = 10, 11 and 12 that one is not among those the beam keeps."""
    best: Cluster | None = None
    for kind in ("fcc", "hcp"):
        sites = lattice_sites(kind, radius=max(2.0, 0.8 * n ** (1 / 3) + 1.5))
        for m, frag in _best_fragments(sites, n, beam):
            if best is not None and m <= best.m:
                break
            c = Cluster.from_coords(sites[list(frag)], params)
            if rigidity(c.coords, c.contacts, params).rigid:
                best = c
                break
    if best is None:  # pragma: no cover - a close-packed fragment grown through triangles is rigid
        raise ValueError(f"no rigid close-packed fragment of {n} spheres found")
    return Cluster(kernels.to_frame(best.coords, triangles(best.contacts)[0]), best.contacts)


@functools.lru_cache(maxsize=8)  # as close_packed_seed: the run's start checks it, then seeds with it
def listed_seed(n: int, min_contacts: int, params: Params = DEFAULT) -> Cluster | None:
    """The rigid fragment with the most contacts (the first listed among equals) of every close-packed
    fragment of n spheres with at least ``min_contacts`` contacts, or None if there is none.  Exhaustive
    where the beam search is not (the maxima of n = 10, 11 and 12 are close-packed fragments it misses),
    and slower: seconds up to n = 13, minutes from n = 14."""
    best: Cluster | None = None
    for f in close_packed(n, min_contacts, params):
        c = f.cluster
        if (best is None or c.m > best.m) and rigidity(c.coords, c.contacts, params).rigid:
            best = c
    return best


def seed_cluster(n: int, params: Params = DEFAULT) -> Cluster:
    """A rigid cluster of n >= 4 spheres to start a run from: a polytetrahedron (3n - 6 contacts), or,
    if the run keeps only clusters with more contacts than that (``params.min_contacts``), a close-packed
    fragment with at least that many: the beam search's (:func:`close_packed_seed`), else the listing's
    (:func:`listed_seed`).  Raises ValueError if no rigid close-packed fragment has that many."""
    if n < 4:
        raise ValueError(f"n must be at least 4, got {n}")
    if params.min_contacts is not None and params.min_contacts > 3 * n - 6:
        c = close_packed_seed(n, params)
        if c.m >= params.min_contacts:
            return c
        listed = listed_seed(n, params.min_contacts, params)
        if listed is None:
            raise ValueError(
                f"no cluster of {n} spheres with at least {params.min_contacts} contacts to start "
                "from: no rigid close-packed fragment has that many"
            )
        return listed
    c = tetrahedron()
    while c.n < n:
        c = glue_sphere(c, params)
    tri = triangles(c.contacts)[0]
    c = Cluster(kernels.to_frame(c.coords, tri), c.contacts)
    rig = rigidity(c.coords, c.contacts, params)
    if not rig.rigid:  # pragma: no cover - a sphere glued to three touching spheres of a rigid cluster is rigid
        raise RuntimeError("seed cluster is not rigid")
    return c
