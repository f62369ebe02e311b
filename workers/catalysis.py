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
4. otherwise the endpoint rule of a path decides (docs/method.md, "The endpoint"): pairs within
   tol_a0 of touching that close to a rigid cluster within tol_a0 make the remainder that cluster
   (:func:`packings.workers.paths.resolve_near_pairs`), else the remainder is kept when the rigidity test
   with its isolation probe calls it rigid (:func:`packings.workers.paths.endpoint_rigidity`); and only
   with at least ``params.min_contacts`` contacts if that is set.

The remainder's coordinates are not projected again: deleting spheres deletes equations, so
the parent's point still solves the remainder's.  Its contacts, measured again from the
coordinates with :func:`packings.workers.cluster.contacts_from_coords` (``params.tol_a``), must be the
inherited ones; they always are (pair distances do not change when other spheres are
deleted), and a remainder where they differ is rejected (``contacts-differ``) rather than
stored with contacts its geometry does not have.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from math import comb
from typing import Iterator

import numpy as np

from packings.workers import kernels
from packings.workers.cluster import Cluster, contacts_from_coords
from packings.workers.outcomes import BELOW_MIN_CONTACTS, NO_TRIANGLE, RIGID
from packings.workers.params import Params
from packings.workers.paths import endpoint_rigidity, resolve_near_pairs
from packings.workers.rigidity import Rigidity, contact_triangle

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
    contacts = tuple((new[i], new[j]) for i, j in parent.contacts if i in new and j in new)
    return Cluster(parent.coords[list(kept)], contacts)


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
