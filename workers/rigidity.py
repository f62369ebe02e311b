"""Rigidity of a cluster: first order, then pre-stress stability (docs/method.md)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.sparse as sp

from packings.workers import kernels
from packings.workers.cluster import pair_set
from packings.workers.params import Params

FIRST_ORDER = "first-order"  #: V empty
PRESTRESS = "prestress"  #: V non-empty, some stress combination makes Q definite
FLOPPY = "floppy"  #: V non-empty and W empty (or held by a rigid part): dimension |V| > 0
UNDECIDED = "undecided"  #: V and W non-empty, no definite combination found
UNRESOLVED_METHOD = "unresolved"  #: Rigidity.method of a pre-stress margin the coordinates leave in doubt


@dataclass(frozen=True)
class Rigidity:
    """What the rigidity test found.

    ``rigid`` is True for first-order rigid and pre-stress stable clusters.
    ``flexes`` = dim V, ``stresses`` = dim W.  ``method`` says which test
    decided (``first-order``, ``single-flex``, ``single-stress``, ``e_k``,
    ``sdp``, ``no-stress``); ``margin`` is the smallest eigenvalue of the best
    stress combination found (or the SDP's t).
    """

    rigid: bool
    kind: str
    flexes: int
    stresses: int
    method: str
    margin: float | None = None

    @property
    def singular(self) -> bool:
        return self.rigid and self.flexes > 0


def stress_forms(V: np.ndarray, W: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Q^(k)_ij = w_k^T R(v_i) v_j = sum_e w_k[e] (v_i[a_e]-v_i[b_e]).(v_j[a_e]-v_j[b_e]).

    Returns an array of shape (b, a, a), symmetric in its last two axes.
    """
    n3, a = V.shape
    vs = V.T.reshape(a, n3 // 3, 3)
    dv = vs[:, edges[:, 0], :] - vs[:, edges[:, 1], :]  # (a, m, 3)
    return np.einsum("ek,iex,jex->kij", W, dv, dv)


@lru_cache(maxsize=None)
def _svec_layout(a: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row and column indices of Clarabel's svec order for a x a matrices, and the weights (1 or sqrt 2)."""
    rows, cols = [], []
    for j in range(a):
        for i in range(j + 1):
            rows.append(i)
            cols.append(j)
    r, c = np.array(rows, dtype=np.int64), np.array(cols, dtype=np.int64)
    w = np.where(r == c, 1.0, np.sqrt(2.0))
    for arr in (r, c, w):
        arr.setflags(write=False)
    return r, c, w


def _svec(m: np.ndarray) -> np.ndarray:
    """Clarabel's scaled vectorisation: upper triangle by columns, off-diagonals times sqrt 2."""
    r, c, w = _svec_layout(m.shape[0])
    return m[r, c] * w


@lru_cache(maxsize=None)
def _sdp_constants(b: int, a: int):
    """The parts of the SDP that depend only on (b, a): box rows, svec(I), right-hand side, cost, cones."""
    svec_len = a * (a + 1) // 2
    a_box = np.hstack([np.vstack([np.eye(b), -np.eye(b)]), np.zeros((2 * b, 1))])
    svec_eye = _svec(np.eye(a))
    rhs = np.concatenate([np.ones(2 * b), np.zeros(svec_len)])
    q = np.zeros(b + 1)
    q[b] = -1.0
    for arr in (a_box, svec_eye, rhs, q):
        arr.setflags(write=False)
    return a_box, svec_eye, rhs, q


def sdp_margin(Q: np.ndarray) -> float | None:
    """max t subject to sum_k c_k Q^(k) - t I >= 0 (PSD), |c_k| <= 1, solved with Clarabel.

    Returns t, or None if the solver did not reach a solution.
    """
    import clarabel

    b, a, _ = Q.shape
    nz = b + 1  # variables c_1..c_b, t
    a_box, svec_eye, rhs, q = _sdp_constants(b, a)
    r, c, w = _svec_layout(a)
    a_psd = np.empty((r.size, nz))
    a_psd[:, :b] = -(Q[:, r, c] * w).T
    a_psd[:, b] = svec_eye
    A = sp.csc_matrix(np.vstack([a_box, a_psd]))
    P = sp.csc_matrix((nz, nz))
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    solver = clarabel.DefaultSolver(
        P, q.copy(), A, rhs.copy(), [clarabel.NonnegativeConeT(2 * b), clarabel.PSDTriangleConeT(a)], settings
    )
    sol = solver.solve()
    if str(sol.status) not in ("Solved", "AlmostSolved"):
        return None
    return float(sol.x[b])


def prestress_test(Q: np.ndarray, tol_psd: float, sdp: bool = True) -> tuple[bool, str, float | None]:
    """Is some combination sum_k c_k Q^(k) definite?  Cheap cases first, the SDP last.

    Returns (rigid, method, margin).  Without ``sdp``, the cheap cases alone: where they find no
    definite combination, (False, ``e_k``, the best margin they found).
    """
    b, a, _ = Q.shape
    if a == 1:
        q = np.abs(Q[:, 0, 0])
        return bool(q.max() > tol_psd), "single-flex", float(q.max())
    best = -np.inf
    for k in range(b):
        ev = np.linalg.eigvalsh(Q[k])
        best = max(best, ev[0], -ev[-1])
        if best > tol_psd:
            return True, "single-stress" if b == 1 else "e_k", float(best)
    if b == 1:
        return False, "single-stress", float(best)
    if not sdp:
        return False, "e_k", float(best)
    t = sdp_margin(Q)
    if t is None:
        return False, "sdp-failed", float(best)
    return bool(t > tol_psd), "sdp", t


def rigidity_without_stress(flexes: int) -> Rigidity:
    """The rigidity test's verdict when W is empty and dim V = ``flexes``: rigid iff there is no flex."""
    if flexes == 0:
        return Rigidity(True, FIRST_ORDER, 0, 0, "first-order")
    return Rigidity(False, FLOPPY, flexes, 0, "no-stress")


def rigidity_from_null_spaces(
    ns: kernels.NullSpaces,
    edges: np.ndarray,
    params: Params,
    x: np.ndarray | None = None,
    free: np.ndarray | None = None,
) -> Rigidity:
    """The rigidity test of docs/method.md given V and W.

    With the point ``x`` (flat, pinned frame) and its ``free`` coordinates, a pre-stress verdict
    "rigid" stands only if the margin exceeds tol_psd by more than the coordinates' accuracy
    can change it (:func:`margin_uncertainty`; otherwise undecided, method ``unresolved``) and x
    is isolated at the scale of the method's probes (:func:`on_a_curve`; otherwise floppy,
    method ``probe``).  Without them (the dimension test, which probes for itself) the
    pre-stress test alone decides.
    """
    a, b = ns.V.shape[1], ns.W.shape[1]
    if b == 0:
        return rigidity_without_stress(a)
    if a == 0:
        return Rigidity(True, FIRST_ORDER, 0, b, "first-order")
    Q = stress_forms(ns.V, ns.W, edges)
    rigid, method, margin = prestress_test(Q, params.tol_psd)
    if rigid and x is not None:
        if margin <= params.tol_psd + margin_uncertainty(x, edges, margin):
            return Rigidity(False, UNDECIDED, a, b, UNRESOLVED_METHOD, margin)
        if on_a_curve(x, edges, free, ns.V, params):
            return Rigidity(False, FLOPPY, a, b, "probe", margin)
    return Rigidity(rigid, PRESTRESS if rigid else UNDECIDED, a, b, method, margin)


def margin_uncertainty(x: np.ndarray, edges: np.ndarray, margin: float) -> float:
    """How far the pre-stress margin computed at x can be from the margin at the solution x stands for.

    Along the flexes the contact residuals grow only to second order, |f| ~ margin d^2 at a
    distance d from a pre-stress stable solution: coordinates with residuals |f| are known along
    the flexes only to d = sqrt(max |f| / margin), and the forms Q, which vary at a rate of order
    one along them, to about d.  A margin no larger than tol_psd + d is not decided by the
    coordinates (docs/method.md).
    """
    f = float(np.abs(kernels.residual(x, edges)).max(initial=0.0))
    return float(np.sqrt(f / margin)) if margin > 0 else np.inf


def on_a_curve(x: np.ndarray, edges: np.ndarray, free: np.ndarray, V: np.ndarray, params: Params) -> bool:
    """Whether the contact equations have solutions at distance eps from x along a flex of V.

    For each flex v, each sign and eps = ds0 and ds0 / 2, x + eps v is projected onto the contacts
    with its correction orthogonal to v; a projection that converges, no further than 2 eps from x,
    is a solution at distance eps along v: x lies on a curve of solutions and is not rigid.  At a
    pre-stress stable point with margin mu the residual on that hyperplane is at least about
    mu eps^2, so such a projection cannot converge (sum f^2 < tol) unless mu < tol / eps^4
    (about 5e-5 at eps = ds0 / 2, a few times tol_psd): this decides what the margin cannot where
    the point lies on a curve of singular points, at which the coordinates are accurate only to
    about sqrt(|f|) and the computed margin is noise (docs/method.md).
    """
    kw = params.newton(stall=params.probe_stall)
    for j in range(V.shape[1]):
        v = V[:, j]
        vf = v[free]
        for eps in (params.ds0, params.ds0 / 2):
            for sign in (1.0, -1.0):
                x0 = x + sign * eps * v
                pr = kernels.project(x0, edges, free, extra=(vf[None, :], np.array([vf @ x0[free]])), **kw)
                if pr.ok and np.linalg.norm(pr.x - x) <= 2 * eps:
                    return True
    return False


def contact_triangle(edges, forbidden=()) -> tuple[int, int, int] | None:
    """The lexicographically first triangle (a, b, c) of contacts, avoiding ``forbidden`` contacts."""
    es = pair_set(edges) - {tuple(e) for e in forbidden}
    nbr: dict[int, set[int]] = {}
    for i, j in es:
        nbr.setdefault(i, set()).add(j)
        nbr.setdefault(j, set()).add(i)
    for i, j in sorted(es):
        common = nbr[i] & nbr[j]
        if common:
            return (i, j, min(common))
    return None


class FirstTriangles:
    """:func:`contact_triangle` of what is left of ``contacts`` (pairs (i, j), i < j) after deleting some of them,
    for many deletions: every triangle (i, j, k), (i, j) a contact and k a common neighbour, in the order in which
    :func:`contact_triangle` looks at them (by (i, j), then k), with the indices of its three contacts; the first
    whose three contacts are all left is the answer."""

    def __init__(self, contacts) -> None:
        contacts = [tuple(map(int, p)) for p in contacts]
        at = {p: q for q, p in enumerate(contacts)}
        nbr: dict[int, set[int]] = {}
        for i, j in contacts:
            nbr.setdefault(i, set()).add(j)
            nbr.setdefault(j, set()).add(i)
        self.triangles = [(i, j, k) for i, j in sorted(contacts) for k in sorted(nbr[i] & nbr[j])]
        self.rows = np.array(
            [(at[(i, j)], at[(min(i, k), max(i, k))], at[(min(j, k), max(j, k))]) for i, j, k in self.triangles],
            dtype=np.int64,
        ).reshape(-1, 3)
        self.m = len(contacts)

    def after_deleting(self, idx) -> tuple[int, int, int] | None:
        """contact_triangle of the contacts left after deleting those at the indices ``idx``."""
        gone = np.zeros(self.m, dtype=bool)
        gone[list(idx)] = True
        left = ~gone[self.rows].any(axis=1)
        return self.triangles[int(left.argmax())] if left.any() else None


def rigidity(coords: np.ndarray, contacts, params: Params) -> Rigidity:
    """Rigidity test of a cluster given its coordinates (n x 3) and contacts."""
    edges = np.array(contacts, dtype=np.int64).reshape(-1, 2)
    tri = contact_triangle(edges)
    if tri is None:
        raise ValueError("cluster has no triangle of contacts to pin")
    n = coords.shape[0]
    x = kernels.to_frame(np.asarray(coords, dtype=np.float64), tri).ravel()
    free = kernels.free_coordinates(n, tri)
    ns = kernels.null_spaces(x, edges, free, params.tol_n)
    return rigidity_from_null_spaces(ns, edges, params, x, free)
