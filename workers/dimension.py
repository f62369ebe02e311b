"""Dimension of the solution set near x after contacts are deleted (docs/method.md)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from packings.workers import kernels
from packings.workers.params import Params
from packings.workers.rigidity import PRESTRESS, Rigidity, prestress_test, rigidity_from_null_spaces, stress_forms

RIGID_PART = "rigid-part"  #: the method of a dimension, or an endpoint's verdict, decided by :func:`rigid_part`


@dataclass(frozen=True)
class Dimension:
    """D, an orthonormal basis of the tangent directions found (3n x D), and how D was decided.

    ``method`` is ``regular`` (R has full row rank: D = |V|), ``rigid-part`` (every
    self-stress lies in a rigid part: D = |V| too, :func:`rigid_part`), ``rigid`` (the
    rigidity test says the point is isolated) or ``numerical`` (tangent-space
    estimate).  A numerical estimate asked to stop above a ``limit`` reports
    ``dim = limit + 1`` when it found more than ``limit`` directions: then D is
    at least that (``at_least`` is True).
    """

    dim: int
    tangents: np.ndarray
    method: str
    rigidity: Rigidity | None = None
    at_least: bool = False
    #: with method ``rigid-part`` and D = 1, rows of the contacts whose deletion leaves R with full row rank and
    #: the same solution set (:func:`held_rows`), or None where no such rows are certified
    held_rows: np.ndarray | None = None


def solution_dimension(
    x: np.ndarray,
    edges: np.ndarray,
    free: np.ndarray,
    params: Params,
    ns: kernels.NullSpaces | None = None,
    limit: int | None = None,
    left: StressBasis | None = None,
) -> Dimension:
    """Dimension of {f = 0} near x, with the pinned coordinates fixed.

    If R has full row rank and no more rows than columns, D = |V|.  So it is too
    where every self-stress lies in an infinitesimally rigid part of the contacts
    (:func:`rigid_part`: the set is then smooth, tangent to V).  Otherwise the
    rigidity test decides D = 0, and failing that the numerical estimate of
    docs/method.md: for each v_j in V and each sign, step to x + s ds0 v_j and project
    back (first with the correction orthogonal to v_j, then, if that fails or is
    rejected, without).  The displacement v_t = x' - x is rejected if
    |v_t| > x_tol_max or |v_t| < x_tol_min; otherwise its part orthogonal to the
    directions already found is kept as a new direction if it is longer than
    v_tol.  With the paper's values (ds0 = 10 ds, x_tol_max = 10 ds,
    x_tol_min = ds / 8, v_tol = 2 ds) a displacement is accepted when it is no
    longer than the probe step, and a new direction needs an orthogonal part of
    a fifth of it: the curvature of a path (about ds0^2 kappa / 2) stays well
    below that, a second genuine direction well above it.

    With ``limit``, the probes stop as soon as more than ``limit`` directions are
    found: the method only asks whether D is 0, 1 or more (``limit=1``), and the
    directions found first, hence D up to the limit and the tangent basis, are
    the same as without it.  Probes that do not converge are the dearest part of
    an expansion, and a set of dimension 2 or more needs none of the rest.

    ``left``, without ``ns``: V and W of the set read off the whole cluster's SVD
    (:func:`left_after_breaking`).  Where they show a rigid part, or a cheap case of
    the pre-stress test finds the set rigid by a margin that an SVD's basis must
    find too (:func:`_rigid_by_left`), the dimension is decided from them, without
    an SVD of the set; otherwise the SVD decides, as without them.
    """
    if ns is None and left is not None:
        found = _held_dimension(x, edges, left, params.tol_n) or _rigid_by_left(edges, left, params)
        if found is not None:
            return found
    if ns is None:
        ns = kernels.null_spaces(x, edges, free, params.tol_n)
    V, W = ns.V, ns.W
    if W.shape[1] == 0:
        return Dimension(V.shape[1], V, "regular")
    if V.shape[1]:
        held = _held_dimension(x, edges, StressBasis.of(ns, params.tol_n, pinv=False), params.tol_n)
        if held is not None:
            return held
    rig = rigidity_from_null_spaces(ns, edges, params)
    if rig.rigid:
        return Dimension(0, V[:, :0], "rigid", rig)
    basis: list[np.ndarray] = []
    for j in range(V.shape[1]):
        for s in (1.0, -1.0):
            vt = _probe(x, V[:, j], s * params.ds0, edges, free, params)
            if vt is None:
                continue
            for b in basis:
                vt = vt - (b @ vt) * b
            r = np.linalg.norm(vt)
            if r > params.v_tol:
                basis.append(vt / r)
                if limit is not None and len(basis) > limit:
                    return Dimension(len(basis), np.stack(basis, axis=1), "numerical", rig, at_least=True)
    t = np.stack(basis, axis=1) if basis else V[:, :0]
    return Dimension(len(basis), t, "numerical", rig)


def _held_dimension(x: np.ndarray, edges: np.ndarray, basis: StressBasis, tol_n: float) -> Dimension | None:
    """D = |V| with V's tangents where every self-stress of ``basis`` (the set's V and W) lies in a rigid part
    (:func:`rigid_part`), with the rows it holds where D = 1 (a path is followed only on a curve); else None."""
    if not basis.flexes or rigid_part(x, edges, basis, tol_n) is None:
        return None
    held = held_rows(basis, tol_n) if basis.flexes == 1 else None
    return Dimension(basis.flexes, basis.V, RIGID_PART, held_rows=held)


#: how far above ``sqrt(stresses) tol_psd`` the margin of a cheap case of the pre-stress test on V and W read
#: off the cluster's SVD must lie for an SVD of the set to find it rigid too (:func:`_rigid_by_left`)
PRESTRESS_GUARD = 2.0


def _rigid_by_left(edges: np.ndarray, left: StressBasis, params: Params) -> Dimension | None:
    """D = 0 where a cheap case of the pre-stress test (no SDP) on the set's V and W read off the cluster's
    SVD (:func:`left_after_breaking`) finds a definite combination with margin above
    :data:`PRESTRESS_GUARD` sqrt(b) tol_psd (b stresses); else None, and the SVD of the set decides.

    The verdict "rigid" is the one the test on an SVD's V and W gives, whose stresses are another
    orthonormal basis of the same space (their flexes too, which leaves the forms' eigenvalues as they
    are).  With one flex, a margin M = max_k |q_k| means |q| >= M, and some coordinate of q in any other
    orthonormal basis is at least |q| / sqrt(b), which ``single-flex`` there finds.  With more, the
    combination found is a unit vector, within the SDP's box |c_k| <= 1 in any orthonormal basis, so that
    test's cheap cases or its SDP find a margin of at least M.  The guard leaves room for rounding."""
    a, b = left.flexes, left.W.shape[1]
    if not a or not b:
        return None
    bound = PRESTRESS_GUARD * np.sqrt(b) * params.tol_psd
    rigid, method, margin = prestress_test(stress_forms(left.V, left.W, edges), bound, sdp=False)
    if not rigid:
        return None
    return Dimension(0, left.V[:, :0], "rigid", Rigidity(True, PRESTRESS, a, b, method, margin))


#: how far from ``tol_n`` a singular value must be, by this factor either way, for the first-order count
#: after deleting rows to be read off the self-stresses (:func:`counts_after_breaking`) rather than an SVD
COUNT_GUARD = 10.0


@dataclass(frozen=True)
class StressBasis:
    """The pinned rigidity matrix R (m x k) of a whole cluster in one frame, summed up by its SVD: what
    :func:`counts_after_breaking` needs to count flexes and stresses after some contacts are deleted."""

    W: np.ndarray  #: m x s, an orthonormal basis of the self-stresses (left null space of R)
    flexes: int  #: f = k - rank(R)
    smallest: float  #: the smallest singular value counted as nonzero (inf if there is none)
    largest: float  #: the largest singular value (0 if there is none)
    noise: float  #: the largest singular value counted as zero (0 if there is none)
    V: np.ndarray | None = None  #: 3n x f, the flexes (full coordinates), for :func:`tangent_after_breaking`
    pinv: np.ndarray | None = None  #: 3n x m, R's pseudo-inverse (full coordinates), likewise

    @classmethod
    def of(cls, ns: kernels.NullSpaces, tol_n: float, pinv: bool = True) -> StressBasis:
        """From an SVD of R; without ``pinv``, no pseudo-inverse (not made where only W and V are asked)."""
        sigma = np.asarray(ns.sigma)
        smallest, noise = _extremes(sigma, tol_n)
        return cls(ns.W, ns.V.shape[1], smallest, float(sigma.max(initial=0.0)), noise, ns.V, ns.pinv if pinv else None)

    def certain(self, guard: float, tol_n: float) -> bool:
        """Whether R's own singular values are far enough from ``tol_n`` for any count to be read off."""
        return _separated(self.smallest, self.noise, guard, tol_n)


def _extremes(sigma: np.ndarray, tol_n: float) -> tuple[float, float]:
    """(the smallest singular value counted nonzero, inf if none; the largest counted zero, 0 if none)."""
    nonzero, zero = sigma[sigma >= tol_n], sigma[sigma < tol_n]
    return float(nonzero.min()) if nonzero.size else np.inf, float(zero.max(initial=0.0))


def _separated(smallest: float, noise: float, guard: float, tol_n: float) -> bool:
    """Whether singular values counted nonzero (the least ``smallest``) and zero (the largest ``noise``) lie
    far enough from ``tol_n``, by the factor ``guard``, for rounding not to change a rank read off them."""
    return smallest - noise >= guard * tol_n and noise <= tol_n / guard


#: a row of R is in the support of the self-stresses where its row of W has at least this norm, and outside
#: it where at most SUPPORT_ZERO; a row in between leaves the support undecided (:func:`rigid_part`)
SUPPORT_NONZERO = 1e-3
SUPPORT_ZERO = 1e-6


def rigid_part(
    x: np.ndarray, edges: np.ndarray, basis: StressBasis, tol_n: float, guard: float = COUNT_GUARD
) -> np.ndarray | None:
    """The spheres of an infinitesimally rigid part of the framework that holds every self-stress of R
    (``basis``: its self-stresses and the bounds on its singular values, from an SVD of R,
    :meth:`StressBasis.of`, or read off a larger matrix's, :func:`left_after_breaking`), or None where none
    is found (or rounding could make the counts other).

    Let B be a set of spheres whose contacts among themselves (R_B, in B's own 3|B| coordinates) have
    rank 3|B| - 6, B not collinear: B is infinitesimally rigid, hence rigid, and near x its spheres move
    as one body.  If moreover rank(R) = rank(R_B) + (contacts not inside B), the contacts not inside B
    are independent of B's, i.e. the framework with B made one body has no self-stress: by the implicit
    function theorem the solution set near x is then a manifold, of dimension 3n - 6 - rank(R) = |V|,
    tangent to V.  With rank(R) = m - s (s self-stresses) the condition reads: the contacts inside B
    number 3|B| - 6 + s.  B is sought among the spheres of the rows where W is not zero (every stress
    lives there), then those with the spheres that touch at least three of B added, until none does.

    Every rank is read off singular values separated from ``tol_n`` as the first-order counts need them
    (:meth:`StressBasis.certain`), and W's rows must have norms either at least :data:`SUPPORT_NONZERO` or
    at most :data:`SUPPORT_ZERO`; otherwise None, and the caller probes as before.  Neither depends on
    which orthonormal basis of the stresses W is (a row's norm is that of the row's projection).
    """
    W = basis.W
    s = W.shape[1]
    if s == 0:
        return None
    if not basis.certain(guard, tol_n):
        return None
    w = np.sqrt(np.einsum("ij,ij->i", W, W))
    if np.any((w > SUPPORT_ZERO) & (w < SUPPORT_NONZERO)):
        return None
    n = x.size // 3
    inside = np.zeros(n, dtype=bool)
    inside[edges[w >= SUPPORT_NONZERO].ravel()] = True
    while True:
        both = inside[edges[:, 0]] & inside[edges[:, 1]]
        if np.count_nonzero(both) == 3 * np.count_nonzero(inside) - 6 + s:
            return _rigid_body(x, edges[both], inside, tol_n, guard)
        one = edges[inside[edges[:, 0]] != inside[edges[:, 1]]]
        touches = np.bincount(np.where(inside[one[:, 0]], one[:, 1], one[:, 0]), minlength=n)
        if not np.any(touches >= 3):
            return None
        inside |= touches >= 3


def held_rows(basis: StressBasis, tol_n: float, guard: float = COUNT_GUARD) -> np.ndarray | None:
    """Where every self-stress lies in a rigid part (:func:`rigid_part`): s rows of the contacts (s = the
    number of self-stresses) whose deletion leaves R with full row rank, sorted; None where the first-order
    count after deleting them (:func:`counts_after_breaking`) is not certain to say so.

    The rows are chosen by a pivoted QR of W^T (greedily, for a well-conditioned s x s block W_S), and must
    lie in the stresses' support, hence inside the rigid part B.  rank(R without S) = rank(R) - s + rank(W_S) =
    rank(R), so the rows of S are combinations of the others, of B's alone (every stress lives in B); B stays
    infinitesimally rigid without them.  The contacts without S then define a manifold of dimension |V| near
    x that holds the set of all of them, itself a manifold of that dimension (:func:`rigid_part`): the same
    set.  Along a path on it B moves as one body, so S keeps its lengths, and the path can be stepped on the
    contacts without S, whose Jacobian has full row rank, at a regular path's cost (docs/method.md,
    "Self-stresses held by a rigid part")."""
    s = basis.W.shape[1]
    if s == 0:
        return None
    _, _, piv = scipy.linalg.qr(basis.W.T, mode="economic", pivoting=True)
    rows = np.sort(piv[:s])
    if np.any(np.linalg.norm(basis.W[rows], axis=1) < SUPPORT_NONZERO):  # outside the support, hence maybe outside B
        return None
    counts = counts_after_breaking(basis, rows, tol_n, guard)
    if counts is None or counts[1] != 0:
        return None
    return rows


def _rigid_body(x: np.ndarray, edges: np.ndarray, inside: np.ndarray, tol_n: float, guard: float) -> np.ndarray | None:
    """The spheres ``inside`` if their contacts ``edges`` make them infinitesimally rigid (rank 3|B| - 6 of
    R_B in their own coordinates, its singular values separated there as :func:`_separated` asks, and the
    spheres not collinear), else None.

    The test depends on the spheres' coordinates and the contacts among them alone, and one expansion asks
    it of the same part for many subsets (those whose broken contacts lie outside it), so it is asked of
    :func:`_rigid_in_own_coordinates`, which remembers its recent answers: the same bytes in, the same
    answer out."""
    spheres = np.nonzero(inside)[0]
    if spheres.size < 3:
        return None
    p = np.ascontiguousarray(x.reshape(-1, 3)[spheres], dtype=np.float64)
    local = np.ascontiguousarray(np.searchsorted(spheres, edges), dtype=np.int64)  # sphere spheres[i] is i
    return spheres if _rigid_in_own_coordinates(p.tobytes(), local.tobytes(), tol_n, guard) else None


@functools.lru_cache(maxsize=4096)
def _rigid_in_own_coordinates(coords: bytes, edges: bytes, tol_n: float, guard: float) -> bool:
    """Whether the spheres at ``coords`` (k x 3 float64) with the contacts ``edges`` among them (pairs of
    int64 in 0..k-1) are infinitesimally rigid and not collinear, as :func:`_rigid_body` asks."""
    p = np.frombuffer(coords, dtype=np.float64).reshape(-1, 3)
    e = np.frombuffer(edges, dtype=np.int64).reshape(-1, 2)
    if np.linalg.svd(p - p.mean(axis=0), compute_uv=False)[1] < 0.1:  # collinear: 5 trivial motions, not 6
        return False
    sv = np.linalg.svd(kernels.rigidity_matrix_numpy(p.ravel(), e), compute_uv=False)
    rank = 3 * p.shape[0] - 6
    return sv.size >= rank and _separated(float(sv[rank - 1]), float(sv[rank:].max(initial=0.0)), guard, tol_n)


def counts_after_breaking(basis: StressBasis, rows, tol_n: float, guard: float = COUNT_GUARD) -> tuple[int, int] | None:
    """(flexes, stresses) of R with ``rows`` deleted (the same frame), as an SVD of that matrix counts
    them with ``tol_n``, read off the self-stresses: or None where rounding could make the SVD count
    otherwise.

    With R = U_r S V_r^T + E (rank r, |E| = ``noise``) and W the self-stresses, [U_r W] is orthogonal,
    so the rows B of U_r satisfy U_B U_B^T = I - W_B W_B^T: the rows of U_r left after deleting B have
    the singular values of W_B (one per deleted row, zero padded) and ones.  Deleting B therefore
    leaves r - |B| singular values of at least ``smallest`` - noise, and one per singular value w of
    W_B between ``smallest`` w - noise and ``largest`` w + noise (Weyl): rank(R without B) =
    r - |B| + rank(W_B), the dual matroid's count, and flexes f + |B| - rank(W_B), stresses
    s - rank(W_B).  Each w must be either so large that the SVD counts its value nonzero, or so small
    that it counts it zero, both by the factor ``guard``; otherwise None (decide by the SVD).
    """
    split = _split(basis, rows, tol_n, guard, vectors=False)
    if split is None:
        return None
    rank_wb = split[0]
    return basis.flexes + len(rows) - rank_wb, basis.W.shape[1] - rank_wb


def _split(basis: StressBasis, rows, tol_n: float, guard: float, vectors: bool) -> tuple[int, np.ndarray | None] | None:
    """(rank of W_B as :func:`counts_after_breaking` counts it, and with ``vectors`` the |B| x (|B| - rank)
    orthonormal basis of the y_B with W_B^T y_B = 0), or None where rounding could make an SVD count
    otherwise."""
    if not basis.certain(guard, tol_n):
        return None
    k = len(rows)
    if not basis.W.shape[1]:  # no self-stress (a regular cluster): W_B is empty, and certain() made its 0 rank sure
        return 0, (np.eye(k) if vectors else None)
    w = np.zeros(k)
    p = None
    wb = basis.W[list(rows)]
    if vectors:
        p, sv, _ = np.linalg.svd(wb, full_matrices=True)
    else:
        sv = np.sqrt(wb @ wb[0]) if k == 1 else np.linalg.svd(wb, compute_uv=False)
    w[: sv.size] = sv
    rank_wb = _rank_of_wb(basis, w, tol_n, guard)
    if rank_wb is None:
        return None
    return rank_wb, (p[:, rank_wb:] if vectors else None)


def _rank_of_wb(basis: StressBasis, w: np.ndarray, tol_n: float, guard: float) -> int | None:
    """The rank of W_B from its singular values ``w`` (descending, zero padded to |B|), each of which must
    leave a singular value of what is left either surely counted nonzero or surely zero
    (:func:`counts_after_breaking`); else None."""
    nonzero = basis.smallest * w - basis.noise >= guard * tol_n
    zero = basis.largest * w + basis.noise <= tol_n / guard
    if not np.all(nonzero | zero):
        return None
    return int(np.count_nonzero(nonzero))


def ranks_after_breaking(
    basis: StressBasis, subsets: list[tuple[int, ...]], tol_n: float, guard: float = COUNT_GUARD
) -> np.ndarray | None:
    """rank(W_B) for each B in ``subsets`` (all of one size k > 1), as :func:`counts_after_breaking` counts it
    without vectors, or -1 where it gives None; None where R's own count is in doubt (it gives None for all).

    The same numbers: the singular values of each k x s matrix W_B from one stacked call, which LAPACK takes
    matrix by matrix as it takes the single one, then the same rule (:func:`_rank_of_wb`)."""
    if not basis.certain(guard, tol_n):
        return None
    if not subsets:
        return np.zeros(0, dtype=np.int64)
    k = len(subsets[0])
    sv = np.linalg.svd(basis.W[np.array(subsets, dtype=np.intp)], compute_uv=False)  # (N, min(k, s)), descending
    w = np.zeros((len(subsets), k))
    w[:, : sv.shape[1]] = sv
    nonzero = basis.smallest * w - basis.noise >= guard * tol_n
    zero = basis.largest * w + basis.noise <= tol_n / guard
    return np.where(np.all(nonzero | zero, axis=1), np.count_nonzero(nonzero, axis=1), -1)


def tangent_after_breaking(basis: StressBasis, rows, tol_n: float, guard: float = COUNT_GUARD) -> np.ndarray | None:
    """The unit tangent (3n, full coordinates) of the set left by deleting ``rows`` where the first-order
    count after it is one flex and no self-stress (:func:`counts_after_breaking`), read off R's SVD in
    that frame; None elsewhere, or where rounding could make an SVD of what is left count otherwise.

    Then R without B has full row rank, so :func:`solution_dimension` would say D = 1 ("regular"), its
    tangent the null vector of R without B.  That null space is R's own flexes plus R^+ y for each
    y in the range of R (orthogonal to every self-stress) that vanishes off B: y_B with W_B^T y_B = 0.
    One flex and no stress left means rank(W_B) = s and f + |B| - s = 1: either f = 1 and |B| = s (the
    tangent is R's flex, its rows of B all used by the stresses), or f = 0 and y_B spans the one
    direction W_B^T leaves (for a regular cluster's single break, y = e_b: the column b of R^-1).  The
    same direction as the SVD of what is left, up to sign and rounding.
    """
    return after_breaking(basis, rows, tol_n, guard)[1]


def after_breaking(
    basis: StressBasis, rows, tol_n: float, guard: float = COUNT_GUARD
) -> tuple[tuple[int, int] | None, np.ndarray | None]:
    """(:func:`counts_after_breaking`, :func:`tangent_after_breaking`) from one SVD of W_B."""
    k, f, s = len(rows), basis.flexes, basis.W.shape[1]
    vectors = f + k - s == 1 and basis.pinv is not None and basis.V is not None
    split = _split(basis, rows, tol_n, guard, vectors)
    if split is None:
        return None, None
    rank_wb, y = split
    counts = (f + k - rank_wb, s - rank_wb)
    if not vectors or counts != (1, 0):
        return counts, None
    if f == 1:
        return counts, basis.V[:, 0].copy()
    t = basis.pinv[:, list(rows)] @ y[:, 0]
    return counts, t / np.linalg.norm(t)


def left_after_breaking(basis: StressBasis, rows, tol_n: float, guard: float = COUNT_GUARD) -> StressBasis | None:
    """The :class:`StressBasis` of R with ``rows`` deleted (the same frame), read off R's own SVD: its
    self-stresses, flexes and bounds on its singular values; None where rounding could make an SVD of what
    is left count otherwise (:func:`counts_after_breaking`), or without R's flexes and pseudo-inverse.

    With W_B = P S Q^T (the SVD of the deleted rows of W, rank r as counted there), the stresses left are
    the combinations of R's that vanish on B, W Q[:, r:] less its rows of B (orthonormal, to the size of
    the singular values counted zero); the flexes are R's own and R^+ y for the y_B that W_B^T leaves,
    P[:, r:] (:func:`tangent_after_breaking`), orthonormalised.  The bounds are those of Weyl's inequality
    that :func:`counts_after_breaking` certifies the counts with: at least the least of ``smallest`` -
    ``noise`` and ``smallest`` w - ``noise`` (w each singular value of W_B counted nonzero) for the values
    counted nonzero, at most the greatest of ``noise`` and ``largest`` w + ``noise`` (w those counted zero)
    for the others; ``largest`` stays a bound, deleting rows making no singular value larger.  They are
    no closer to ``tol_n`` than the SVD's own values (to rounding, about eps ``largest``), so a test of
    separation (:meth:`StressBasis.certain`) passes only where the SVD's values would pass it too."""
    if basis.V is None or basis.pinv is None or not basis.W.shape[1] or not basis.certain(guard, tol_n):
        return None
    rows = list(rows)
    k = len(rows)
    p, sv, qt = np.linalg.svd(basis.W[rows], full_matrices=True)
    w = np.zeros(k)
    w[: sv.size] = sv
    r = _rank_of_wb(basis, w, tol_n, guard)
    if r is None:
        return None
    kept = np.ones(basis.W.shape[0], dtype=bool)
    kept[rows] = False
    W = (basis.W @ qt[r:].T)[kept]
    t = basis.pinv[:, rows] @ p[:, r:]
    if t.shape[1] == 1:
        t = t / np.linalg.norm(t)
    elif t.shape[1]:
        t = np.linalg.qr(t)[0]
    smallest = min([basis.smallest - basis.noise] + [basis.smallest * v - basis.noise for v in w[:r]])
    noise = max([basis.noise] + [basis.largest * v + basis.noise for v in w[r:]])
    return StressBasis(W, basis.flexes + k - r, smallest, basis.largest, noise, np.hstack([basis.V, t]))


def may_decide(basis: StressBasis, k: int) -> bool:
    """Whether the first-order count after deleting k rows can show a set that is not one-dimensional
    (no flex left, or no stress and a number of flexes other than one) for some rank of W_B (0 up to
    min(k, s)): where it cannot, :func:`counts_after_breaking` need not be asked."""
    f, s = basis.flexes, basis.W.shape[1]
    return any(f + k - r == 0 or (s == r and f + k - r != 1) for r in range(min(k, s) + 1))


def _probe(x, v, step, edges, free, params: Params) -> np.ndarray | None:
    """Displacement x' - x to the solution set from x + step v, or None if it is rejected."""
    x0 = x + step * v
    kw = params.newton()
    attempts = [(None, 0)]
    if orthogonal_may_be_accepted(x0, edges, step, float(np.linalg.norm(v[free])), params):
        attempts.insert(0, ((v[free][None, :], np.array([v[free] @ x0[free]])), params.probe_stall))
    for extra, stall in attempts:
        pr = kernels.project(x0, edges, free, extra=extra, stall=stall, **kw)
        if pr.ok and params.x_tol_min <= np.linalg.norm(pr.x - x) <= params.x_tol_max:
            return pr.x - x
    return None


def orthogonal_may_be_accepted(x0: np.ndarray, edges: np.ndarray, step: float, v_norm: float, params: Params) -> bool:
    """False when no point the orthogonal projection of a probe can converge to is accepted.

    The probe starts at x0 = x + step v, at distance d = |step| |v| from x.  A
    point x' where that projection converges satisfies every contact to
    |f_k(x')| < sqrt(tol) and the orthogonality row to w.(x' - x0) = r with
    |r| < sqrt(tol) / |v| (w = v / |v|).  Then w.(x' - x) = d + r (up to sign),
    and accepting x' needs |x' - x| <= x_tol_max, so
    |x' - x0|^2 = r^2 + |x' - x|^2 - (d + r)^2 <= x_tol_max^2 - d^2 + 2 d |r| = eps^2.
    A contact (i, j) changes by at most |(x' - x0)_i - (x' - x0)_j| <= sqrt(2) eps
    between x0 and x', so f_k(x0) = |d_k(x') - delta|^2 - 1 is at most
    sqrt(tol) + 2 sqrt(2) sqrt(1 + sqrt(tol)) eps + 2 eps^2 in size.  If some
    contact's residual at x0 is larger (with a margin of 1 % for round-off), or
    eps^2 < 0, the orthogonal projection could only be rejected, and is not run:
    this changes no result.  With the paper's values (x_tol_max = ds0, so eps is
    about 5.5e-5 and the bound 1.5e-4) it excluded every probe of n = 10 and 11,
    where f(x0) is of the order of ds0^2 |v_i - v_j|^2.
    """
    root = np.sqrt(params.tol)
    if v_norm <= 0.0:
        return True
    d = abs(step) * v_norm
    eps2 = params.x_tol_max**2 - d**2 + 2.0 * d * root / v_norm
    if eps2 < 0.0:
        return False
    eps = np.sqrt(eps2)
    bound = root + 2.0 * np.sqrt(2.0) * np.sqrt(1.0 + root) * eps + 2.0 * eps2
    return float(np.max(np.abs(kernels.residual(x0, edges)), initial=0.0)) <= 1.01 * bound
