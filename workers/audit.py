"""Auditing a stored cluster: its near pairs, and what adding them as contacts gives (pure numerics).

A stored cluster whose smallest non-contact gap is a few ``tol_a`` may be a junk
"near copy": a point on a path that passed close by a cluster, stored with a
near contact left out (docs/method.md).  Genuine clusters can
have small gaps too (at n = 13 down to about 6e-5), so each near pair is tested:
the cluster is projected onto its contacts and the pair(s), and the result, if it
is rigid, is looked up among the stored clusters by the caller
(:mod:`packings.service.audit`).

Whether a cluster stands for an exact one is :mod:`packings.workers.exact`'s
question (docs/method.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from packings.workers import kernels
from packings.workers.cluster import Cluster, Contact, pair_distances
from packings.workers.params import Params
from packings.workers.paths import close_pairs, overlaps
from packings.workers.rigidity import Rigidity, contact_triangle, rigidity

RIGID = "rigid"  #: projected onto the added contacts, no overlap, and rigid
NOT_RIGID = "not-rigid"  #: projected, no overlap, but the rigidity test fails (floppy or undecided)
DOES_NOT_PROJECT = "does-not-project"  #: Newton's method found no point with every contact and the pairs
OVERLAP = "overlap"  #: projected, but two spheres then overlap by more than tol_a


@dataclass(frozen=True)
class NearPair:
    """A pair of spheres that do not touch (distance >= 1 + tol_a) but are within tol_a0 of touching."""

    i: int
    j: int
    gap: float  #: distance - 1

    @property
    def pair(self) -> Contact:
        return (self.i, self.j)


def near_pairs(cluster: Cluster, tol_a0: float) -> tuple[NearPair, ...]:
    """The non-contact pairs of ``cluster`` whose distance is below 1 + ``tol_a0``, smallest gap first.

    ``tol_a0`` is the distance at which a path stops for a new contact: a pair
    this close is one a path would have closed, so a stored cluster with one is
    suspect of being a near copy of the cluster with that contact.
    """
    d = pair_distances(cluster.coords)
    near = np.triu((d < 1.0 + tol_a0) & ~cluster.adjacency(), k=1)
    out = [NearPair(int(i), int(j), float(d[i, j] - 1.0)) for i, j in zip(*np.nonzero(near))]
    return tuple(sorted(out, key=lambda p: (p.gap, p.i, p.j)))


@dataclass(frozen=True)
class Added:
    """What adding ``pairs`` to a cluster's contacts gives.

    ``cluster`` and ``moved`` are set when the projection succeeded (also for
    ``overlap`` and ``not-rigid``), ``rigidity`` when there was no overlap.
    ``moved`` is the largest coordinate difference between the cluster and the
    projected one after the optimal alignment (the measure of
    :func:`packings.workers.identity.geometry_distance`, with the labels kept).
    """

    pairs: tuple[Contact, ...]
    status: str
    cluster: Cluster | None = None
    rigidity: Rigidity | None = None
    moved: float | None = None


def with_contacts_added(cluster: Cluster, pairs, params: Params) -> Added:
    """Project ``cluster`` onto its contacts and ``pairs`` and say what it becomes.

    As a path's endpoint is treated (:func:`packings.workers.paths.close_pairs`: polished projection,
    adjacency with tol_a and projection onto every contact, an overlapping point returned as
    it is), but with no bound on how far the spheres move, so that the audit can say how far
    the cluster it stands for is; the endpoint rule accepts it only within tol_a0
    (``moved``, compared by :mod:`packings.service.audit`).  An overlap (a pair closer than
    1 - tol_a) is rejected, and the rest is given the rigidity test.
    """
    pairs = tuple(sorted((min(int(i), int(j)), max(int(i), int(j))) for i, j in pairs))
    tri = contact_triangle(cluster.edges())
    if tri is None:
        raise ValueError("cluster has no triangle of contacts to pin")
    free = kernels.free_coordinates(cluster.n, tri)
    x = kernels.to_frame(cluster.coords, tri).ravel()
    closed = close_pairs(
        x, cluster.edges(), np.array(pairs, dtype=np.int64).reshape(-1, 2), free, params.with_(tol_a0=np.inf)
    )
    if closed is None:
        return Added(pairs, DOES_NOT_PROJECT)
    coords = closed[0].reshape(-1, 3)
    new = Cluster(coords, closed[1])
    moved = _moved(cluster.coords, coords)
    if overlaps(closed[0], params):
        return Added(pairs, OVERLAP, new, None, moved)
    rig = rigidity(coords, new.contacts, params)
    return Added(pairs, RIGID if rig.rigid else NOT_RIGID, new, rig, moved)


def _moved(before: np.ndarray, after: np.ndarray) -> float:
    """Largest coordinate difference between two labellings-alike configurations after the optimal
    alignment (centred, orthogonal Procrustes, reflections allowed)."""
    a = before - before.mean(axis=0)
    b = after - after.mean(axis=0)
    return kernels.aligned_max_error(b, a)


def what_adding_gives(cluster: Cluster, near: tuple[NearPair, ...], params: Params) -> tuple[Added, ...]:
    """:func:`with_contacts_added` for each near pair alone, then, when there are several, for all of
    them together (the order of the result).

    Each alone, because a near copy usually misses one contact (adding it may
    bring further near pairs into contact: :func:`with_contacts_added` projects
    again with them); all together, because a path that passes by a cluster can
    miss several at once.  The n = 12 near misses of tests/data each have two
    near pairs at 2.5e-4 and either one alone closes both.
    """
    out = [with_contacts_added(cluster, [p.pair], params) for p in near]
    if len(near) > 1:
        out.append(with_contacts_added(cluster, [p.pair for p in near], params))
    return tuple(out)
