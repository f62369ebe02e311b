"""Cluster representation: centres of n unit-diameter spheres and their contacts."""

from __future__ import annotations

import functools
import operator
from dataclasses import dataclass

import numpy as np

from packings.workers.params import DEFAULT, Params

Contact = tuple[int, int]


def cross3(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """u x v for two 3-vectors (np.cross costs about ten times as much on one pair)."""
    return np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])


def pair_distances(x: np.ndarray) -> np.ndarray:
    """Matrix of |x_i - x_j| for all pairs (n x n, zero diagonal)."""
    d = x[:, None, :] - x[None, :, :]
    return np.sqrt(np.einsum("ijk,ijk->ij", d, d))


@functools.lru_cache(maxsize=None)
def upper_pairs(n: int) -> np.ndarray:
    """Every pair (i < j) of n spheres, row by row (read-only, shared)."""
    pairs = np.stack(np.triu_indices(n, 1), axis=1).astype(np.int64)
    pairs.setflags(write=False)
    return pairs


#: every contact pair made so far, each once: clusters, broken subsets and formed contacts hold these
#: very tuples rather than copies (an expansion of a cluster with many contacts holds hundreds of
#: thousands of subsets and endpoints; n spheres have only n(n - 1)/2 pairs)
_PAIRS: dict[Contact, Contact] = {}


def pair(i: int, j: int) -> Contact:
    """The contact (min, max) of spheres i and j, as the one shared tuple of that pair."""
    p = (i, j) if i < j else (j, i)
    return _PAIRS.setdefault(p, p)


def contacts_from_distances(pairs: np.ndarray, d: np.ndarray, tol_a: float) -> tuple[Contact, ...]:
    """The rows (i, j) of ``pairs`` whose distance ``d`` is below 1 + tol_a, in the order of ``pairs``:
    the one rule of what is a contact, whoever computed the distances."""
    return tuple(pair(i, j) for i, j in pairs[d < 1.0 + tol_a].tolist())


def contacts_from_coords(x: np.ndarray, tol_a: float) -> tuple[Contact, ...]:
    """Pairs (i, j), i < j, with |x_i - x_j| < 1 + tol_a, sorted."""
    p = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    pairs = upper_pairs(len(p))
    d = p[pairs[:, 0]] - p[pairs[:, 1]]
    return contacts_from_distances(pairs, np.sqrt(np.einsum("ij,ij->i", d, d)), tol_a)


def pair_set(contacts) -> set[Contact]:
    """The pairs (i, j) of ``contacts`` as a set: a cluster's tuple of pairs as it is, anything else (an
    array of rows, a list) read as rows of two ints."""
    if type(contacts) is tuple and (not contacts or type(contacts[0]) is tuple):
        return set(contacts)
    return set(map(tuple, np.asarray(contacts, dtype=np.int64).reshape(-1, 2).tolist()))


def normalise_contacts(contacts) -> tuple[Contact, ...]:
    """Contacts as a sorted tuple of (i, j) with i < j and no repeats."""
    if type(contacts) is tuple and _normal(contacts):
        return contacts
    if isinstance(contacts, np.ndarray):  # its rows as Python ints at once, not numpy scalars one by one
        contacts = contacts.tolist()
    return tuple(sorted({pair(int(a), int(b)) for a, b in contacts}))


def _normal(contacts: tuple) -> bool:
    """Whether ``contacts`` is already what :func:`normalise_contacts` makes of it: the shared tuples of
    :func:`pair` (so each (i, j) of ints with i < j), strictly increasing.  Every path endpoint's contacts
    are (:func:`contacts_from_distances`); checked at C speed, as a cluster is made for each endpoint."""
    try:
        shared = all(map(operator.is_, map(_PAIRS.get, contacts), contacts))
        return shared and all(map(operator.lt, contacts, contacts[1:]))
    except TypeError:  # an unhashable element (a list): not a shared pair
        return False


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


@dataclass(frozen=True, eq=False)
class Cluster:
    """n sphere centres (n x 3, float64) and their contact pairs (sorted, i < j)."""

    coords: np.ndarray
    contacts: tuple[Contact, ...]

    def __post_init__(self) -> None:
        x = np.ascontiguousarray(self.coords, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 3:
            raise ValueError(f"coordinates must be n x 3, got shape {x.shape}")
        x.setflags(write=False)
        object.__setattr__(self, "coords", x)
        object.__setattr__(self, "contacts", normalise_contacts(self.contacts))

    @classmethod
    def of_normal(cls, coords: np.ndarray, contacts: tuple[Contact, ...]) -> "Cluster":
        """The cluster of ``coords``, a new n x 3 float64 array of its own, and ``contacts``, already what
        :func:`normalise_contacts` makes of them (sorted shared pairs :func:`pair`), taken as they are: for
        the many clusters catalysis makes from one parent."""
        c = object.__new__(cls)
        coords.setflags(write=False)
        object.__setattr__(c, "coords", coords)
        object.__setattr__(c, "contacts", contacts)
        return c

    @classmethod
    def from_coords(cls, coords, params: Params = DEFAULT) -> "Cluster":
        """The cluster whose contacts are the pairs closer than 1 + tol_a."""
        x = np.asarray(coords, dtype=np.float64)
        return cls(x, contacts_from_coords(x, params.tol_a))

    @property
    def n(self) -> int:
        return self.coords.shape[0]

    @property
    def m(self) -> int:
        return len(self.contacts)

    def edges(self) -> np.ndarray:
        """Contacts as an (m x 2) integer array."""
        return np.array(self.contacts, dtype=np.int64).reshape(-1, 2)

    def adjacency(self) -> np.ndarray:
        a = np.zeros((self.n, self.n), dtype=bool)
        e = self.edges()
        a[e[:, 0], e[:, 1]] = True
        a[e[:, 1], e[:, 0]] = True
        return a

    def min_distance(self) -> float:
        """Smallest distance between two sphere centres (>= 1 - tol when valid)."""
        d = pair_distances(self.coords)
        return float(d[np.triu_indices(self.n, 1)].min())

    def closest_pair(self) -> tuple[int, int, float] | None:
        """(i, j, gap) of the two spheres not in contact that are closest (i < j, the first such pair
        in row order on a tie), gap = their distance minus 1; None if every pair touches."""
        d = pair_distances(self.coords)
        mask = np.triu(~self.adjacency(), k=1)
        if not mask.any():
            return None
        i, j = divmod(int(np.argmin(np.where(mask, d, np.inf))), self.n)
        return i, j, float(d[i, j] - 1.0)

    def min_gap(self) -> float:
        """Smallest distance between two non-touching spheres, minus 1 (inf if none)."""
        pair = self.closest_pair()
        return float("inf") if pair is None else pair[2]

    def to_dict(self) -> dict:
        return {"coords": self.coords.tolist(), "contacts": [list(c) for c in self.contacts]}

    @classmethod
    def from_dict(cls, d: dict) -> "Cluster":
        return cls(np.array(d["coords"], dtype=np.float64), tuple(tuple(c) for c in d["contacts"]))
