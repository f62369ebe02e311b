"""Rigid starting clusters for any n: polytetrahedra built by gluing spheres onto contact triangles."""

from __future__ import annotations

import numpy as np

from packings.workers import kernels
from packings.workers.cluster import Cluster
from packings.workers.params import DEFAULT, Params
from packings.workers.rigidity import rigidity


def triangles(contacts) -> list[tuple[int, int, int]]:
    """All triangles (i < j < k) of mutually touching spheres."""
    nbr: dict[int, set[int]] = {}
    for i, j in contacts:
        nbr.setdefault(i, set()).add(j)
        nbr.setdefault(j, set()).add(i)
    out = []
    for i, j in contacts:
        for k in sorted(nbr[i] & nbr[j]):
            if k > j:
                out.append((i, j, k))
    return sorted(out)


def cap_positions(p: np.ndarray, tri: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The two points at distance 1 from each sphere of a unit triangle (either side of its plane).

    For a triangle of unit-distance spheres the apex sits above the centroid at
    height sqrt(2/3).
    """
    a, b, c = (p[i] for i in tri)
    centroid = (a + b + c) / 3.0
    normal = np.cross(b - a, c - a)
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


def seed_cluster(n: int, params: Params = DEFAULT) -> Cluster:
    """A rigid cluster of n >= 4 spheres with 3n - 6 contacts (a polytetrahedron)."""
    if n < 4:
        raise ValueError(f"n must be at least 4, got {n}")
    c = tetrahedron()
    while c.n < n:
        c = glue_sphere(c, params)
    tri = triangles(c.contacts)[0]
    c = Cluster(kernels.to_frame(c.coords, tri), c.contacts)
    rig = rigidity(c.coords, c.contacts, params)
    if not rig.rigid:  # pragma: no cover - a sphere glued to three touching spheres of a rigid cluster is rigid
        raise RuntimeError("seed cluster is not rigid")
    return c

