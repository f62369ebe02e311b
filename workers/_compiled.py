"""Compiled (numba) implementations of the hot loop of :mod:`packings.workers.kernels` and :mod:`packings.workers.paths`.

Nothing outside :mod:`packings.workers.kernels` and :mod:`packings.workers.paths` should import this
module: :mod:`packings.workers.kernels` is the interface, and selects between these
functions and the plain numpy reference (``packings.workers.kernels.set_backend``).

Numerics (docs/method.md), exactly as in the numpy reference up to round-off:

* Coordinates are full 3n vectors; ``mask`` is 1.0 on the free coordinates and
  0.0 on the six pinned ones, so R_f (the pinned rigidity matrix) acts as
  R(x) diag(mask).
* A Newton step is the minimum-norm solution of J dx = -f with J = [2 R_f; A]
  (A: optional extra linear rows).  When J has full row rank that is
  dx = J^T y with (J J^T) y = -f, solved by Cholesky.  The Gram matrix
  R_f R_f^T is assembled from the contact graph (two rows overlap only when
  their contacts share a sphere).
* Rank guard (rigorous): with L the Cholesky factor of G = R_f R_f^T, the
  smallest eigenvalue of G is at most every pivot^2, and at least
  1 / (||M^{-1}||_1 ||M^{-1}||_inf) for the comparison matrix M of L (two
  O(m^2) triangular solves) and at least 1 / ||L^{-1}||_F^2 (O(m^3), tried
  only when the first bound is too weak).  The guard is (100 tol_n)^2
  (``packings.workers.kernels.guard_threshold``).
* Newton steps use the normal equations only where the guard certifies
  J J^T, and otherwise the same least-squares step as the reference's LAPACK
  solve (by QR factorisations where they are certified, else by LAPACK).
  Convergence is always judged on the residual itself, and a projection that
  fails after using the normal equations is redone without them, so that no
  failure (which shortens the step) comes of their rounding.
* At every point a path reaches the tangent is computed here only when the
  guard certifies R_f R_f^T there; on the first step the dimension is then the
  reference's "regular" |V| = k - m.  Otherwise (Cholesky fails, or more
  contacts than free coordinates) the first step goes back to Python, which
  uses the SVD (``kernels.null_spaces``) and the dimension test exactly as the
  reference does; later steps take the SVD's tangent here (_svd_tangent), or,
  where R_f loses rank only through rows that are combinations of others to
  rounding, the same projection without the SVD (_reduced_tangent).
* The tangent is carried by projecting the previous one onto the null space of
  R_f: t - R_f^T (R_f R_f^T)^{-1} R_f t, with one step of iterative refinement.
  Where the guard passes, every singular value of R_f is at least
  sqrt(guard) >> tol_n, so the SVD's null space (singular values < tol_n) is
  exactly the orthogonal complement of the row space and this is the same
  projector as V V^T.
"""

from __future__ import annotations

import numba
import numpy as np

# Status codes returned by follow_steps (mirrored in packings.workers.paths).
ST_HIT = 0  #: an approaching pair is within 1 + tol_a0: xn and the hit mask are the endpoint's input
ST_NEED_SVD = 1  #: xn (the first step) is projected and checked; the guard failed there, so its dimension needs Python
ST_PROJECTION_FAILED = 2
ST_SHORTENS = 3
ST_DIMENSION_CHANGED = 4  #: the projected tangent vanished (returned steps already counts this step)
ST_TOO_LONG = 5

# Status codes of newton (mirrored in packings.workers.kernels).
NEWTON_OK = 0
NEWTON_FAILED = 1

#: the guard of _newton_step that refuses the normal equations at every step and leaves each to the QR, reduced
#: or LAPACK step (the re-check of a failure, _newton_ws); no Gram matrix is certified above it
NO_NORMAL = np.finfo(np.float64).max

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@numba.njit(**_JIT)
def _dist2(x, i, j):
    """|x_i - x_j|^2 (flat coordinates)."""
    s = 0.0
    for c in range(3):
        d = x[3 * i + c] - x[3 * j + c]
        s += d * d
    return s


@numba.njit(**_JIT)
def residual(x, edges):
    """f_k = |x_i - x_j|^2 - 1 for each contact k = (i, j)."""
    m = edges.shape[0]
    f = np.empty(m)
    for k in range(m):
        f[k] = _dist2(x, edges[k, 0], edges[k, 1]) - 1.0
    return f


@numba.njit(**_JIT)
def rigidity_matrix(x, edges):
    """Dense R(x) (m x 3n): row k = (i, j) has x_i - x_j in i's columns and x_j - x_i in j's."""
    m = edges.shape[0]
    r = np.zeros((m, x.size))
    for k in range(m):
        i = edges[k, 0]
        j = edges[k, 1]
        for c in range(3):
            d = x[3 * i + c] - x[3 * j + c]
            r[k, 3 * i + c] = d
            r[k, 3 * j + c] = -d
    return r


@numba.njit(**_JIT)
def pair_distances_flat(x, pairs):
    """|x_i - x_j| for each (i, j) in ``pairs``."""
    k = pairs.shape[0]
    out = np.empty(k)
    for p in range(k):
        out[p] = np.sqrt(_dist2(x, pairs[p, 0], pairs[p, 1]))
    return out


# ----------------------------------------------------------------------------- linear algebra


@numba.njit(**_JIT)
def _incidence(edges, n):
    """CSR lists of the contacts at each sphere: ptr (n + 1), contact index and sign (+1 for i, -1 for j)."""
    m = edges.shape[0]
    deg = np.zeros(n + 1, dtype=np.int64)
    for k in range(m):
        deg[edges[k, 0] + 1] += 1
        deg[edges[k, 1] + 1] += 1
    for s in range(n):
        deg[s + 1] += deg[s]
    ptr = deg.copy()
    fill = deg[:n].copy()
    idx = np.empty(2 * m, dtype=np.int64)
    sign = np.empty(2 * m)
    for k in range(m):
        i = edges[k, 0]
        j = edges[k, 1]
        idx[fill[i]] = k
        sign[fill[i]] = 1.0
        fill[i] += 1
        idx[fill[j]] = k
        sign[fill[j]] = -1.0
        fill[j] += 1
    return ptr, idx, sign


@numba.njit(**_JIT)
def _differences(x, edges, D):
    """D[k] = x_i - x_j for contact k = (i, j)."""
    for k in range(edges.shape[0]):
        i = edges[k, 0]
        j = edges[k, 1]
        for c in range(3):
            D[k, c] = x[3 * i + c] - x[3 * j + c]


@numba.njit(**_JIT)
def _gram(D, mask, ptr, idx, sign, scale, G):
    """G[:m, :m] = scale * R_f R_f^T, from the contacts meeting at each sphere."""
    m = D.shape[0]
    n = ptr.size - 1
    for a in range(m):
        for b in range(m):
            G[a, b] = 0.0
    for s in range(n):
        m0 = mask[3 * s]
        m1 = mask[3 * s + 1]
        m2 = mask[3 * s + 2]
        for p in range(ptr[s], ptr[s + 1]):
            k = idx[p]
            for q in range(p, ptr[s + 1]):
                l = idx[q]
                v = (
                    sign[p]
                    * sign[q]
                    * scale
                    * (m0 * D[k, 0] * D[l, 0] + m1 * D[k, 1] * D[l, 1] + m2 * D[k, 2] * D[l, 2])
                )
                G[k, l] += v
                if l != k:
                    G[l, k] += v


@numba.njit(**_JIT)
def _rmul(D, edges, mask, v, out):
    """out[:m] = R_f v (v a full 3n vector)."""
    for k in range(edges.shape[0]):
        i = edges[k, 0]
        j = edges[k, 1]
        s = 0.0
        for c in range(3):
            s += D[k, c] * (mask[3 * i + c] * v[3 * i + c] - mask[3 * j + c] * v[3 * j + c])
        out[k] = s


@numba.njit(**_JIT)
def _rtmul_add(D, edges, mask, y, scale, out):
    """out += scale * R_f^T y[:m] (a full 3n vector, zero in the pinned coordinates)."""
    for k in range(edges.shape[0]):
        i = edges[k, 0]
        j = edges[k, 1]
        yk = scale * y[k]
        for c in range(3):
            out[3 * i + c] += mask[3 * i + c] * D[k, c] * yk
            out[3 * j + c] -= mask[3 * j + c] * D[k, c] * yk


@numba.njit(**_JIT)
def _cholesky(G, L, size):
    """L L^T = G[:size, :size] (lower triangle of L written).  False if a pivot is not positive.

    Left-looking: L[i, j] = (G[i, j] - sum_{p < j} L[i, p] L[j, p]) / L[j, j], each sum taken in the
    order p = 0, 1, ..., j - 1.  Four rows i go through the loop over p together: four
    independent sums, each in that order, so the factor is the one-row loop's bit for bit, faster where
    one sum's latency would otherwise hold the loop.
    """
    for j in range(size):
        s = G[j, j]
        for p in range(j):
            s -= L[j, p] * L[j, p]
        if not s > 0.0:  # also catches nan
            return False
        ljj = np.sqrt(s)
        L[j, j] = ljj
        i = j + 1
        while i + 3 < size:
            t0 = G[i, j]
            t1 = G[i + 1, j]
            t2 = G[i + 2, j]
            t3 = G[i + 3, j]
            for p in range(j):
                a = L[j, p]
                t0 -= L[i, p] * a
                t1 -= L[i + 1, p] * a
                t2 -= L[i + 2, p] * a
                t3 -= L[i + 3, p] * a
            L[i, j] = t0 / ljj
            L[i + 1, j] = t1 / ljj
            L[i + 2, j] = t2 / ljj
            L[i + 3, j] = t3 / ljj
            i += 4
        while i < size:
            t = G[i, j]
            for p in range(j):
                t -= L[i, p] * L[j, p]
            L[i, j] = t / ljj
            i += 1
    return True


@numba.njit(**_JIT)
def _eig_lower_bound(L, size, work):
    """1 / ||L^{-1}||_F^2: a lower bound on the smallest eigenvalue of L L^T.

    Column j of L^{-1} by forward substitution from row j (_forward_rows: u[:j] = 0), its squares added to
    the total in the order of its rows."""
    total = 0.0
    e = np.zeros(size)
    for j in range(size):  # column j of L^{-1}: solve L u = e_j (u[:j] = 0)
        e[j] = 1.0
        _forward_rows(L, j, size, e, work)
        e[j] = 0.0
        for i in range(j, size):
            total += work[i] * work[i]
    if not total > 0.0 or not np.isfinite(total):
        return 0.0
    return 1.0 / total


@numba.njit(**_JIT)
def _forward_solve(L, size, b, out):
    """out[:size] = L^{-1} b[:size] (L lower triangular; b may be out)."""
    _forward_rows(L, 0, size, b, out)


@numba.njit(**_JIT)
def _forward_rows(L, start, size, b, out):
    """out[i] = (b[i] - sum_{start <= p < i} L[i, p] out[p]) / L[i, i] for i = start, ..., size - 1: forward
    substitution in L[start:size, start:size] (b may be out).

    Each sum in the order p = start, start + 1, ...; four rows at a time share the loop over the p before
    them (as in _cholesky), then finish in order, so the result is the one-row loop's bit for bit."""
    i = start
    while i + 3 < size:
        s0 = b[i]
        s1 = b[i + 1]
        s2 = b[i + 2]
        s3 = b[i + 3]
        for p in range(start, i):
            o = out[p]
            s0 -= L[i, p] * o
            s1 -= L[i + 1, p] * o
            s2 -= L[i + 2, p] * o
            s3 -= L[i + 3, p] * o
        o0 = s0 / L[i, i]
        s1 -= L[i + 1, i] * o0
        o1 = s1 / L[i + 1, i + 1]
        s2 -= L[i + 2, i] * o0
        s2 -= L[i + 2, i + 1] * o1
        o2 = s2 / L[i + 2, i + 2]
        s3 -= L[i + 3, i] * o0
        s3 -= L[i + 3, i + 1] * o1
        s3 -= L[i + 3, i + 2] * o2
        out[i] = o0
        out[i + 1] = o1
        out[i + 2] = o2
        out[i + 3] = s3 / L[i + 3, i + 3]
        i += 4
    while i < size:
        s = b[i]
        for p in range(start, i):
            s -= L[i, p] * out[p]
        out[i] = s / L[i, i]
        i += 1


@numba.njit(**_JIT)
def _backward_solve(L, size, b, out):
    """out[:size] = L^{-T} b[:size] (L lower triangular; b may be out)."""
    for i in range(size - 1, -1, -1):
        s = b[i]
        for p in range(i + 1, size):
            s -= L[p, i] * out[p]
        out[i] = s / L[i, i]


@numba.njit(**_JIT)
def _chol_solve(L, size, b, out):
    """out = (L L^T)^{-1} b[:size]."""
    _forward_solve(L, size, b, out)
    _backward_solve(L, size, out, out)


@numba.njit(**_JIT)
def _fill_free_rows(x, edges, free, scale, out):
    """out[:m] = scale R(x)[:, free] (row k = (i, j): x_i - x_j in i's free columns, x_j - x_i in j's);
    the other entries of those rows are left as they are (zero in a new matrix)."""
    pos = np.full(x.size, -1, dtype=np.int64)
    for c in range(free.size):
        pos[free[c]] = c
    for r in range(edges.shape[0]):
        i = edges[r, 0]
        j = edges[r, 1]
        for c in range(3):
            d = scale * (x[3 * i + c] - x[3 * j + c])
            if pos[3 * i + c] >= 0:
                out[r, pos[3 * i + c]] = d
            if pos[3 * j + c] >= 0:
                out[r, pos[3 * j + c]] = -d


@numba.njit(**_JIT)
def _fill_jacobian(x, edges, free, A, J):
    """J[:m + e, :k] = the Jacobian of the contacts and the extra rows A in the free columns (J may be a
    transposed view)."""
    m = edges.shape[0]
    _fill_free_rows(x, edges, free, 2.0, J)
    for r in range(A.shape[0]):
        for c in range(free.size):
            J[m + r, c] = A[r, free[c]]


@numba.njit(**_JIT)
def _lstsq_step(x, edges, free, A, f, dx_full):
    """The reference's Newton step: minimum-norm least squares by LAPACK (as numpy.linalg.lstsq)."""
    m = edges.shape[0]
    e = A.shape[0]
    k = free.size
    n3 = x.size
    J = np.zeros((m + e, k))
    _fill_jacobian(x, edges, free, A, J)
    rhs = np.empty(m + e)
    for r in range(m + e):
        rhs[r] = -f[r]
    rcond = np.finfo(np.float64).eps * max(m + e, k)
    sol = np.linalg.lstsq(J, rhs, rcond)[0]
    for c in range(n3):
        dx_full[c] = 0.0
    for c in range(k):
        dx_full[free[c]] = sol[c]


#: the QR step (_qr_step) is taken only where every singular value of J is at least this times its largest
#: (by a lower bound); below, LAPACK's least squares is, which counts a singular value as zero only
#: below eps max(rows, columns) times the largest (about 1e-14 here)
QR_MIN_RATIO = 1e-10


@numba.njit(**_JIT)
def _certified_qr(M):
    """M = Q U (M with at least as many rows as columns): (Q, L = U^T, whether every singular value of M is
    at least QR_MIN_RATIO times the largest).  L is the Cholesky factor of M^T M up to the signs of its
    columns, so 1 / ||L^-1||_F^2 bounds sigma_min(M)^2 from below, and ||L||_F = ||M||_F bounds sigma_max."""
    Q, U = np.linalg.qr(M)
    L = U.T.copy()
    return Q, L, _ratio_certified(L)


@numba.njit(**_JIT)
def _ratio_certified(L):
    """Whether every singular value of M is at least QR_MIN_RATIO times the largest, for L L^T = M^T M
    (L = U^T of _certified_qr's QR): 1 / ||L^-1||_F^2 <= sigma_min(M)^2, ||L||_F^2 >= sigma_max(M)^2."""
    size = L.shape[0]
    work = np.empty(size)
    low = _eig_lower_bound(L, size, work)
    top = 0.0
    for i in range(size):
        for j in range(i + 1):
            top += L[i, j] * L[i, j]
    return low >= QR_MIN_RATIO * QR_MIN_RATIO * top


@numba.njit(**_JIT)
def _qr_least_squares(Q, L, rows, cols, f, out):
    """out[:cols] = -U^-1 Q^T f[:rows] (U = L^T, Q rows x cols): the least-squares solution of M y = -f for
    M = Q U of full column rank."""
    work = np.empty(cols)
    for c in range(cols):
        s = 0.0
        for r in range(rows):
            s += Q[r, c] * f[r]
        work[c] = -s
    _backward_solve(L, cols, work, out)


@numba.njit(**_JIT)
def _qr_step(x, edges, free, A, f, dx_full):
    """The same minimum-norm least-squares step as _lstsq_step, by a QR factorisation, where J has full rank
    with every singular value at least QR_MIN_RATIO times the largest; returns False (dx_full untouched)
    elsewhere.

    At most as many rows as free columns: J^T = Q U (U upper triangular), so J = U^T Q^T and the
    minimum-norm solution of J dx = -f is dx = Q y with U^T y = -f.  More rows (a hyperstatic point, or
    the contacts and a probe's row): J = Q U with full column rank, so the least-squares solution is
    unique, the minimum-norm one LAPACK's least squares computes (which truncates nothing above eps
    max(rows, columns) times the largest singular value), dx = -U^-1 Q^T f.  Like the SVD's both are
    backward stable: the steps differ by about cond(J) times the rounding unit (cond(J)^2 for an
    inconsistent system with more rows).
    """
    m = edges.shape[0]
    e = A.shape[0]
    k = free.size
    size = m + e
    if size == 0:
        return False
    tall = size > k
    if tall:
        J = np.zeros((size, k))
        _fill_jacobian(x, edges, free, A, J)
        Q, L, ok = _certified_qr(J)
    else:
        Jt = np.zeros((k, size))
        _fill_jacobian(x, edges, free, A, Jt.T)
        Q, L, ok = _certified_qr(Jt)
    if not ok:
        return False
    rank = min(size, k)
    work = np.empty(rank)
    y = np.empty(rank)
    if tall:
        _qr_least_squares(Q, L, size, k, f, y)
    else:
        for i in range(size):
            work[i] = -f[i]
        _forward_solve(L, size, work, y)  # U^T y = -f
    for c in range(x.size):
        dx_full[c] = 0.0
    for c in range(k):
        if tall:
            dx_full[free[c]] = y[c]
        else:
            s = 0.0
            for r in range(size):
                s += Q[c, r] * y[r]
            dx_full[free[c]] = s
    return True


#: a row of J is dropped as a combination of the others (_reduced_step) only where all the rows so dropped
#: differ from combinations of the rows kept by at most this fraction of LAPACK's own threshold for a zero
#: singular value (eps max(rows, columns) times the largest, here the largest row norm, no larger), so that the
#: singular values they leave are below it with room for LAPACK's own rounding: LAPACK counts them zero too
DEPENDENT_FRACTION = 0.5
#: rows whose pivot^2 in a Cholesky of J J^T is below this times their diagonal are taken for dependent (a guess,
#: which _reduced_step then checks on J itself: the Gram matrix cannot resolve it)
_DEPENDENT_PIVOT = 1e-12
#: a row further than this times the largest row norm from the span of the rows kept, measured through the
#: normal equations, is no combination of them (_far_from_kept; their error is far below this)
_NEARLY = 1e-8


@numba.njit(**_JIT)
def _independent_rows(G, size, keep, L):
    """A Cholesky of G[:size, :size] that skips every row whose pivot^2 is below _DEPENDENT_PIVOT times its
    diagonal: the rows kept, in order, in keep[:r], and L[:r, :r] the factor of G on them; returns r."""
    row = np.empty(size)
    r = 0
    for j in range(size):
        s = G[j, j]
        for p in range(r):
            t = G[j, keep[p]]
            for q in range(p):
                t -= row[q] * L[p, q]
            row[p] = t / L[p, p]
            s -= row[p] * row[p]
        if s > _DEPENDENT_PIVOT * G[j, j]:
            for p in range(r):
                L[r, p] = row[p]
            L[r, r] = np.sqrt(s)
            keep[r] = j
            r += 1
    return r


@numba.njit(**_JIT)
def _far_from_kept(J, G, keep, kept, L, r, bound):
    """Whether some row of J not in keep[:r] (``kept`` False) is further than ``bound`` from the span of the rows kept, by the
    normal equations on G's factor L: a cheap test that refuses the rows that are only nearly dependent (too
    coarse to accept any: _reduced_step then measures on J itself)."""
    b = np.empty(r)
    c = np.empty(r)
    k = J.shape[1]
    for i in range(J.shape[0]):
        if kept[i]:
            continue
        for p in range(r):
            b[p] = G[keep[p], i]
        _chol_solve(L, r, b, c)
        left = 0.0
        for col in range(k):
            v = J[i, col]
            for p in range(r):
                v -= c[p] * J[keep[p], col]
            left += v * v
        if np.sqrt(left) > bound:
            return True
    return False


@numba.njit(**_JIT)
def _split_rows(M, G, size):
    """The rows of M (size x k, G = M M^T up to a positive factor) split into rows kept and rows that are
    combinations of them: (r, keep, Q, L, C, left).  keep[:r] are the rows kept (_independent_rows),
    M_I^T = Q U with L = U^T (uncertified: the caller bounds L's singular values as it needs); C[i] the
    coefficients on Q's columns of each row i not kept; ``left`` the norm
    (summed in squares) of what is left of those rows after projecting onto Q, against DEPENDENT_FRACTION of
    LAPACK's threshold for a zero singular value: dependent to rounding where left <= 1.  r = -1 where no row
    is dropped, none is kept, the rows kept have full column rank, or the rows dropped are far from their span
    by the cheap test through the normal equations (_far_from_kept)."""
    k = M.shape[1]
    keep = np.empty(size, dtype=np.int64)
    LG = np.zeros((size, size))
    r = _independent_rows(G, size, keep, LG)
    Q = np.empty((0, 0))
    C = np.zeros((size, max(r, 0)))
    if r == size or r == 0 or r >= k:  # nothing dropped, or full column rank left: _qr_step's case
        return -1, keep, Q, Q, C, np.inf
    rowmax = 0.0
    for i in range(size):
        s = 0.0
        for c in range(k):
            s += M[i, c] * M[i, c]
        rowmax = max(rowmax, np.sqrt(s))
    kept = np.zeros(size, dtype=np.bool_)
    for p in range(r):
        kept[keep[p]] = True
    if _far_from_kept(M, G, keep, kept, LG, r, _NEARLY * rowmax):
        return -1, keep, Q, Q, C, np.inf
    MIt = np.empty((k, r))
    for p in range(r):
        for c in range(k):
            MIt[c, p] = M[keep[p], c]
    Q, U = np.linalg.qr(MIt)
    L = U.T.copy()
    left = 0.0
    for i in range(size):
        if kept[i]:
            continue
        for p in range(r):
            s = 0.0
            for c in range(k):
                s += Q[c, p] * M[i, c]
            C[i, p] = s
        for c in range(k):
            s = M[i, c]
            for p in range(r):
                s -= Q[c, p] * C[i, p]
            left += s * s
    threshold = DEPENDENT_FRACTION * np.finfo(np.float64).eps * max(size, k) * rowmax
    return r, keep, Q, L, C, np.sqrt(left) / threshold


@numba.njit(**_JIT)
def _reduced_step(x, edges, free, A, f, G, dx_full):
    """LAPACK's minimum-norm least-squares step (_lstsq_step) where J is rank deficient because some of its rows
    are combinations of the others (a self-stress that persists wherever the point moves, as when a hyperstatic
    set of contacts is kept), by two QR factorisations of full-rank matrices instead of an SVD; returns False
    (dx_full untouched) where that cannot be shown to be LAPACK's step.

    The rows to drop are guessed from a Cholesky of G = J J^T (up to a positive factor) that skips small
    pivots (_independent_rows).  The rows kept, J_I^T = Q U, must have every singular value at least
    QR_MIN_RATIO times the largest; the rows dropped must lie in their span to DEPENDENT_FRACTION of LAPACK's
    threshold (the norm of what is left of them after projecting onto Q, summed in squares): _split_rows.
    Then J is J' = T Q^T (T = J Q) plus a matrix below that threshold, whose singular values LAPACK counts
    zero, and J' has rank r = |I|: the least-squares step of smallest norm is dx = Q z with z the
    least-squares solution of T z = -f (QR of T, certified like the other), the solution LAPACK computes up
    to rounding.
    """
    k = free.size
    size = edges.shape[0] + A.shape[0]
    if size == 0:
        return False
    J = np.zeros((size, k))
    _fill_jacobian(x, edges, free, A, J)
    r, keep, Q, L, T, left = _split_rows(J, G, size)
    if r < 0 or not left <= 1.0 or not _ratio_certified(L):
        return False
    for p in range(r):
        for q in range(p + 1):
            T[keep[p], q] = L[p, q]  # J_I = U^T Q^T: T's rows of I are U^T = L; the others are C
    QT, LT, ok = _certified_qr(T)
    if not ok:
        return False
    z = np.empty(r)
    _qr_least_squares(QT, LT, size, r, f, z)
    for c in range(x.size):
        dx_full[c] = 0.0
    for c in range(k):
        s = 0.0
        for p in range(r):
            s += Q[c, p] * z[p]
        dx_full[free[c]] = s
    return True


@numba.njit(**_JIT)
def _full_residual(x, edges, A, b, f):
    """f[:m] = contact residuals, f[m:] = A x - b; returns sum f^2."""
    m = edges.shape[0]
    fsq = 0.0
    for k in range(m):
        f[k] = _dist2(x, edges[k, 0], edges[k, 1]) - 1.0
        fsq += f[k] * f[k]
    for r in range(A.shape[0]):
        s = 0.0
        for c in range(x.size):
            s += A[r, c] * x[c]
        f[m + r] = s - b[r]
        fsq += f[m + r] * f[m + r]
    return fsq


@numba.njit(**_JIT)
def _workspace(n3, edges, e):
    """Work arrays for Newton and the tangent: (ptr, idx, sign, D, G, L, f, y, work, dx)."""
    m = edges.shape[0]
    size = m + e
    ptr, idx, sign = _incidence(edges, n3 // 3)
    return (
        ptr,
        idx,
        sign,
        np.empty((m, 3)),
        np.empty((size, size)),
        np.zeros((size, size)),
        np.empty(size),
        np.empty(size),
        np.empty(max(size, n3)),
        np.empty(n3),
    )


@numba.njit(**_JIT)
def _comparison_lower_bound(L, size, work):
    """1 / (||M^{-1}||_1 ||M^{-1}||_inf), M = M(L) the comparison matrix of L: a lower bound on lambda_min(L L^T).

    M has |L_ii| on the diagonal and -|L_ij| off it; |L^{-1}| <= M^{-1} entrywise
    (Higham, Accuracy and Stability of Numerical Algorithms, Thm 8.12), so
    ||L^{-1}||_2^2 <= ||L^{-1}||_1 ||L^{-1}||_inf <= ||M^{-1}||_1 ||M^{-1}||_inf, and
    lambda_min(L L^T) = 1 / ||L^{-1}||_2^2.  M^{-1} >= 0, so its norms are
    max(M^{-1} e) and max(M^{-T} e): two triangular solves with no cancellation.
    """
    row = 0.0
    i = 0
    while i + 3 < size:  # M z = e, four rows at a time as in _forward_solve (the same sums in the same order)
        s0 = 1.0
        s1 = 1.0
        s2 = 1.0
        s3 = 1.0
        for p in range(i):
            w = work[p]
            s0 += abs(L[i, p]) * w
            s1 += abs(L[i + 1, p]) * w
            s2 += abs(L[i + 2, p]) * w
            s3 += abs(L[i + 3, p]) * w
        w0 = s0 / L[i, i]
        s1 += abs(L[i + 1, i]) * w0
        w1 = s1 / L[i + 1, i + 1]
        s2 += abs(L[i + 2, i]) * w0
        s2 += abs(L[i + 2, i + 1]) * w1
        w2 = s2 / L[i + 2, i + 2]
        s3 += abs(L[i + 3, i]) * w0
        s3 += abs(L[i + 3, i + 1]) * w1
        s3 += abs(L[i + 3, i + 2]) * w2
        w3 = s3 / L[i + 3, i + 3]
        work[i] = w0
        work[i + 1] = w1
        work[i + 2] = w2
        work[i + 3] = w3
        row = max(row, w0)
        row = max(row, w1)
        row = max(row, w2)
        row = max(row, w3)
        i += 4
    while i < size:
        s = 1.0
        for p in range(i):
            s += abs(L[i, p]) * work[p]
        work[i] = s / L[i, i]
        row = max(row, work[i])
        i += 1
    col = 0.0
    for i in range(size - 1, -1, -1):  # M^T z = e
        s = 1.0
        for p in range(i + 1, size):
            s += abs(L[p, i]) * work[p]
        work[i] = s / L[i, i]
        col = max(col, work[i])
    prod = row * col
    if not prod > 0.0 or not np.isfinite(prod):
        return 0.0
    return 1.0 / prod


@numba.njit(**_JIT)
def _certify(L, size, threshold, work):
    """Is lambda_min(L L^T) >= threshold?  Rigorous (up to rounding far below the thresholds used).

    A small pivot refutes (lambda_min <= every pivot^2).  Then two lower bounds
    are tried, the O(size^2) comparison-matrix bound first, the O(size^3)
    1 / ||L^{-1}||_F^2 only if that one is too weak.
    """
    for r in range(size):
        if L[r, r] * L[r, r] < threshold:
            return False
    if _comparison_lower_bound(L, size, work) >= threshold:
        return True
    return _eig_lower_bound(L, size, work) >= threshold


@numba.njit(**_JIT)
def _qr_or_reduced_step(which, x, edges, free, A, f, G, dx):
    """_reduced_step if ``which`` is 1, _qr_step if 0 (the order of _newton_step)."""
    if which == 1:
        return _reduced_step(x, edges, free, A, f, G, dx)
    return _qr_step(x, edges, free, A, f, dx)


@numba.njit(**_JIT)
def _newton_step(x, edges, free, mask, A, f, guard, ws, order):
    """dx = minimum-norm solution of J dx = -f (full 3n vector, in ws[9]).

    By the normal equations (J J^T) y = -f, dx = J^T y when the smallest
    eigenvalue of J J^T is certified to be at least 4 guard (J J^T = 4 R_f R_f^T
    on the contacts); otherwise by a QR factorisation of J^T (of J where it has more
    rows than free columns) where J is far from rank deficient (_qr_step), by two QR
    factorisations where J loses rank only through rows that are combinations of
    others (_reduced_step), and else by LAPACK least squares, as the reference.
    A guard of NO_NORMAL (the re-check of a failure) refuses the normal equations
    at every step, so that the QR, reduced or LAPACK step takes each; a guard of
    inf takes LAPACK's least squares at every step.  Returns True if the normal
    equations were used.

    The QR and the reduced steps never both take a step: where _reduced_step does, J is within rounding
    of a rank below min(rows, columns) (the rows it drops lie in the span of the others to DEPENDENT_FRACTION
    of LAPACK's threshold), so its smallest singular value is below that threshold, far under QR_MIN_RATIO
    times its largest, and _qr_step refuses.  Which is asked first therefore changes no step, only what a
    refusal costs (a QR for _qr_step, a Cholesky of G for _reduced_step, when J has no dependent rows):
    ``order[0]`` is 1 to ask _reduced_step first, 0 for _qr_step, and is set to the one that took the step,
    so that the steps of one projection, or of one path (where a self-stress persists, every step), ask the
    one that served the last.
    """
    ptr, idx, sign, D, G, L, _, y, work, dx = ws
    m = edges.shape[0]
    e = A.shape[0]
    size = m + e
    _differences(x, edges, D)
    if e == 0:
        # (4 R_f R_f^T) y = -f, dx = 2 R_f^T y, solved as (R_f R_f^T) z = -f / 2, dx = R_f^T z
        # (the same numbers: the factors are powers of two)
        _gram(D, mask, ptr, idx, sign, 1.0, G)
        ok = size > 0 and guard < NO_NORMAL and _cholesky(G, L, size) and _certify(L, size, guard, work)
        scale = 0.5
    else:
        _gram(D, mask, ptr, idx, sign, 4.0, G)
        for r in range(e):  # extra rows: G[m + r, :m] = 2 A_r R_f^T, G[m + r, m + s] = A_r A_s^T (A zero when pinned)
            _rmul(D, edges, mask, A[r], work)
            for k in range(m):
                G[m + r, k] = 2.0 * work[k]
                G[k, m + r] = 2.0 * work[k]
            for s2 in range(e):
                t = 0.0
                for c in range(x.size):
                    t += A[r, c] * A[s2, c]
                G[m + r, m + s2] = t
        ok = guard < NO_NORMAL and _cholesky(G, L, size) and _certify(L, size, 4.0 * guard, work)
        scale = 1.0
    if not ok:
        taken = False
        if guard < np.inf:
            first = order[0]
            taken = _qr_or_reduced_step(first, x, edges, free, A, f, G, dx)
            if not taken and _qr_or_reduced_step(1 - first, x, edges, free, A, f, G, dx):
                taken, order[0] = True, 1 - first
        if not taken:
            _lstsq_step(x, edges, free, A, f, dx)
        return False
    for r in range(size):
        work[r] = -scale * f[r]
    _chol_solve(L, size, work, y)
    for c in range(x.size):
        dx[c] = 0.0
    _rtmul_add(D, edges, mask, y, 2.0 * scale, dx)
    for r in range(e):
        for c in range(x.size):
            dx[c] += A[r, c] * y[m + r]
    return True


@numba.njit(**_JIT)
def _newton_core(x0, edges, free, mask, A, b, tol, dx_max, max_iter, polish, guard, ws, stall, order):
    """The iteration of packings.workers.kernels.project_numpy; returns (x, status, iterations, sum f^2, normal steps).

    ``stall`` > 0: fail once sum f^2 has not gone below its smallest value so far for
    that many consecutive iterations (before convergence); 0: never.  ``order`` as in _newton_step.
    """
    f = ws[6]
    dx = ws[9]
    x = x0.copy()
    best_x = x.copy()
    best_fsq = np.inf
    fsq = np.inf
    converged = False
    n_normal = 0
    low = np.inf
    since = 0
    for it in range(max_iter + 1):
        fsq = _full_residual(x, edges, A, b, f)
        if not np.isfinite(fsq):
            break
        if converged:
            if fsq > 0.5 * best_fsq:
                return best_x, NEWTON_OK, it, best_fsq, n_normal
            best_x[:] = x
            best_fsq = fsq
            if fsq == 0.0:  # exact: every further step is zero
                return best_x, NEWTON_OK, it, fsq, n_normal
        elif fsq < tol:
            if not polish or fsq == 0.0:
                return x, NEWTON_OK, it, fsq, n_normal
            converged = True
            best_x[:] = x
            best_fsq = fsq
        elif stall > 0:
            if fsq < low:
                low = fsq
                since = 0
            else:
                since += 1
                if since >= stall:
                    return x, NEWTON_FAILED, it, fsq, n_normal
        if it == max_iter:
            break
        if _newton_step(x, edges, free, mask, A, f, guard, ws, order):
            n_normal += 1
        step = 0.0
        for c in range(x.size):
            step += dx[c] * dx[c]
        step = np.sqrt(step)
        if step > dx_max:
            r = dx_max / step
            for c in range(x.size):
                dx[c] *= r
        for c in range(free.size):
            x[free[c]] += dx[free[c]]
    if converged:
        return best_x, NEWTON_OK, max_iter, best_fsq, n_normal
    return x, NEWTON_FAILED, max_iter, fsq, n_normal


@numba.njit(**_JIT)
def _newton_ws(x0, edges, free, mask, A, b, tol, dx_max, max_iter, polish, guard, ws, order, stall=0):
    """Newton by the normal equations; a failure is re-checked without them.

    A projection that fails after using the normal equations is redone from x0
    with every step a backward-stable least-squares step (the QR or reduced step
    where it is certified, LAPACK's otherwise: the steps the reference's least
    squares computes, up to rounding), so that no reported failure comes of the
    normal equations' rounding (cond(J)^2 where theirs is cond(J)).  A projection
    that fails with no normal-equation step is not redone: it already is such an
    iteration.  Returns (x, status, iterations, sum f^2, normal-equation steps,
    retried).  ``order`` as in _newton_step.
    """
    x, st, it, fsq, nn = _newton_core(
        x0, edges, free, mask, A, b, tol, dx_max, max_iter, polish, guard, ws, stall, order
    )
    if st == NEWTON_OK or nn == 0:
        return x, st, it, fsq, nn, False
    x, st, it, fsq, nn2 = _newton_core(
        x0, edges, free, mask, A, b, tol, dx_max, max_iter, polish, NO_NORMAL, ws, stall, order
    )
    return x, st, it, fsq, nn + nn2, True


@numba.njit(**_JIT)
def newton(x0, edges, free, mask, A, b, tol, dx_max, max_iter, polish, guard, stall=0):
    """Newton projection, the same iteration as packings.workers.kernels.project (see there).

    ``A`` (e x 3n, zero in pinned columns) and ``b`` are the extra linear rows
    (e = 0 for none); ``stall`` as in _newton_core.  Returns (x, status,
    iterations, sum f^2, normal-equation steps, whether a failure was retried by
    least squares).
    """
    ws = _workspace(x0.size, edges, A.shape[0])
    return _newton_ws(
        x0, edges, free, mask, A, b, tol, dx_max, max_iter, polish, guard, ws, np.zeros(1, np.int64), stall
    )


@numba.njit(**_JIT)
def _full_row_rank(x, edges, mask, guard, ws):
    """Cholesky of R_f R_f^T at x into ws[5]; True if it certifies lambda_min >= guard (full row rank)."""
    ptr, idx, sign, D, G, L, _, _, work, _ = ws
    m = edges.shape[0]
    if m == 0:
        return True
    _differences(x, edges, D)
    _gram(D, mask, ptr, idx, sign, 1.0, G)
    if not _cholesky(G, L, m):
        return False
    return _certify(L, m, guard, work)


@numba.njit(**_JIT)
def regular_flexes(x, edges, free, mask, guard):
    """k - m (k = free coordinates) if the guard certifies that R_f has full row rank m <= k, else -1.

    Certified means every singular value of R_f is at least sqrt(guard): then the
    SVD with threshold tol_n << sqrt(guard) has rank m, no left null space and a
    right null space of dimension k - m.
    """
    m = edges.shape[0]
    if m > free.size:
        return -1
    ws = _workspace(x.size, edges, 0)
    if _full_row_rank(x, edges, mask, guard, ws):
        return free.size - m
    return -1


@numba.njit(**_JIT)
def _project_tangent(x, edges, mask, t, ws, tn):
    """tn = t - R_f^T (R_f R_f^T)^{-1} R_f t at x, with the factor from _full_row_rank (one refinement pass)."""
    _, _, _, D, _, L, r, z, _, _ = ws
    m = edges.shape[0]
    for c in range(x.size):
        tn[c] = mask[c] * t[c]
    if m == 0:
        return
    for _ in range(2):  # projection, then one refinement of the same projection
        _rmul(D, edges, mask, tn, r)
        _chol_solve(L, m, r, z)
        _rtmul_add(D, edges, mask, z, -1.0, tn)


@numba.njit(**_JIT)
def _svd_tangent(x, edges, free, t, tol_n, tn):
    """tn = V V^T t with V the right null space of R_f at x by the SVD (singular values below tol_n are
    zero), as packings.workers.paths._svd_tangent after the first step; returns |tn| (0 when V is empty).

    The tangent where the rank guard cannot certify full row rank (a self-stress persists along the
    path), in the loop instead of a return to Python for numpy's SVD."""
    k = free.size
    n3 = x.size
    R = np.zeros((edges.shape[0], k))
    _fill_free_rows(x, edges, free, 1.0, R)
    _, sv, vt = np.linalg.svd(R)
    rank = 0
    for q in range(sv.size):
        if sv[q] >= tol_n:
            rank += 1
    for c in range(n3):
        tn[c] = 0.0
    if rank >= k:
        return 0.0
    for q in range(rank, k):
        a = 0.0
        for c in range(k):
            a += vt[q, c] * t[free[c]]
        for c in range(k):
            tn[free[c]] += a * vt[q, c]
    norm = 0.0
    for c in range(n3):
        norm += tn[c] * tn[c]
    return np.sqrt(norm)


@numba.njit(**_JIT)
def _reduced_tangent(x, edges, free, mask, t, guard, ws, tn):
    """tn = V V^T t as _svd_tangent computes it, where R_f loses rank only through rows that are combinations of
    others: returns |tn|, or -1.0 where that cannot be shown (then the SVD decides).

    The rows kept (_split_rows on R_f), R_I^T = Q U, must have every singular value at least sqrt(guard) =
    100 tol_n (the rank guard's bound on L = U^T), and the rows dropped must lie in their span to
    DEPENDENT_FRACTION of LAPACK's threshold for a zero singular value.  Then the SVD counts exactly |I|
    singular values of R_f at least tol_n and the others below it, and its null space V is the orthogonal
    complement of Q's columns up to rounding: V V^T t = t - Q Q^T t on the free coordinates.
    """
    ptr, idx, sign, D, G, _, _, _, work, _ = ws
    m = edges.shape[0]
    k = free.size
    if m == 0:
        return -1.0
    _differences(x, edges, D)
    _gram(D, mask, ptr, idx, sign, 1.0, G)
    R = np.zeros((m, k))
    _fill_free_rows(x, edges, free, 1.0, R)
    r, _, Q, L, _, left = _split_rows(R, G, m)
    if r < 0 or not left <= 1.0 or not _eig_lower_bound(L, r, work) >= guard:
        return -1.0
    coef = np.empty(r)
    for p in range(r):
        s = 0.0
        for c in range(k):
            s += Q[c, p] * t[free[c]]
        coef[p] = s
    for c in range(x.size):
        tn[c] = 0.0
    norm = 0.0
    for c in range(k):
        v = t[free[c]]
        for p in range(r):
            v -= Q[c, p] * coef[p]
        tn[free[c]] = v
        norm += v * v
    return np.sqrt(norm)


@numba.njit(**_JIT)
def follow_steps(
    x,
    t,
    d_prev,
    h,
    h_max,
    steps,
    first_pending,
    edges,
    free,
    mask,
    pairs,
    broken_idx,
    ds,
    h_min,
    tol,
    dx_max,
    max_iter,
    tol_a0,
    max_steps,
    guard,
    stop_on_dimension_change,
    tol_n,
):
    """The stepping loop of packings.workers.paths.follow_path, until Python is needed.

    Mirrors the reference loop step for step.  At each projected point the rank
    guard either certifies that R_f has full row rank, and the tangent is the
    projection of the previous one onto the null space (on the first step the
    dimension is then k - m, the reference's "regular" branch), or the tangent is
    the SVD's (:func:`_svd_tangent`, singular values below ``tol_n`` zero), except
    on the first step, where the loop returns ST_NEED_SVD and Python decides the
    dimension (packings.workers.dimension.solution_dimension) and the tangent.

    Returns (status, x, t, d_prev, h, h_max, steps, first_dim, xn, d, hit, stats)
    where x, t, d_prev, h, h_max, steps are the loop state (for resuming),
    first_dim the dimension after the first step (-1: not known here), xn / d
    the last projected point and its pair distances (for ST_HIT and
    ST_NEED_SVD), ``hit`` the mask of pairs that ended the path (ST_HIT) and
    stats = [steps taken here, Newton projections, normal-equation Newton steps,
    projections retried by least squares, steps handed to the SVD].

    One function of about 130 lines on purpose: the whole loop is one compiled call per path, its state
    in locals and one workspace, with no Python between steps (docs/performance.md).
    """
    n3 = x.size
    m = edges.shape[0]
    k = free.size
    npairs = pairs.shape[0]
    ws = _workspace(n3, edges, 0)
    tn = np.empty(n3)
    noA = np.zeros((0, n3))
    nob = np.zeros(0)
    x = x.copy()
    t = t.copy()
    d_prev = d_prev.copy()
    xp = np.empty(n3)
    hit = np.zeros(npairs, dtype=np.bool_)
    xn = x.copy()
    d = d_prev.copy()
    first_dim = -1
    stats = np.zeros(5, dtype=np.int64)
    order = np.zeros(1, dtype=np.int64)  # which of the QR and reduced steps to ask first (_newton_step), along the path
    while steps < max_steps:
        for c in range(n3):
            xp[c] = x[c] + h * t[c]
        xn, st, _, _, nn, retried = _newton_ws(
            xp, edges, free, mask, noA, nob, tol, dx_max, max_iter, False, guard, ws, order
        )
        stats[1] += 1
        stats[2] += nn
        if retried:
            stats[3] += 1
        forward = 0.0
        for c in range(n3):
            forward += (xn[c] - x[c]) * t[c]
        if st != NEWTON_OK or forward <= 0.0:
            h /= 2
            if h < h_min:
                return ST_PROJECTION_FAILED, x, t, d_prev, h, h_max, steps, first_dim, xn, d, hit, stats
            continue
        d = pair_distances_flat(xn, pairs)
        if first_pending:
            for q in range(broken_idx.size):
                if d[broken_idx[q]] <= d_prev[broken_idx[q]]:
                    return ST_SHORTENS, x, t, d_prev, h, h_max, steps, first_dim, xn, d, hit, stats
        any_hit = False
        overlap = False
        for p in range(npairs):
            hit[p] = d[p] < d_prev[p] and d[p] < 1.0 + tol_a0
            if hit[p]:
                any_hit = True
                if d[p] < 1.0 - tol_a0:
                    overlap = True
        if any_hit:
            if h_max > ds:  # back up and approach with the small step
                h_max = ds
                h = min(h, h_max)
                continue
            if overlap:
                h /= 2
                if h < h_min:
                    return ST_PROJECTION_FAILED, x, t, d_prev, h, h_max, steps, first_dim, xn, d, hit, stats
                continue
            return ST_HIT, x, t, d_prev, h, h_max, steps, first_dim, xn, d, hit, stats
        if m > k or not _full_row_rank(xn, edges, mask, guard, ws):
            stats[4] += 1
            if first_pending:
                return ST_NEED_SVD, x, t, d_prev, h, h_max, steps, first_dim, xn, d, hit, stats
            norm = _reduced_tangent(xn, edges, free, mask, t, guard, ws, tn)
            if norm < 0.0:
                norm = _svd_tangent(xn, edges, free, t, tol_n, tn)
        else:
            if first_pending:  # the reference's solution_dimension, "regular" branch: D = |V| = k - m
                first_pending = False
                first_dim = k - m
                if first_dim == 0 or (first_dim > 1 and stop_on_dimension_change):
                    return ST_DIMENSION_CHANGED, x, t, d_prev, h, h_max, steps + 1, first_dim, xn, d, hit, stats
            _project_tangent(xn, edges, mask, t, ws, tn)
            norm = 0.0
            for c in range(n3):
                norm += tn[c] * tn[c]
            norm = np.sqrt(norm)
        if norm < 1e-8:
            return ST_DIMENSION_CHANGED, x, t, d_prev, h, h_max, steps + 1, first_dim, xn, d, hit, stats
        for c in range(n3):
            t[c] = tn[c] / norm
        x[:] = xn
        d_prev[:] = d
        steps += 1
        stats[0] += 1
        h = min(2 * h, h_max)
    return ST_TOO_LONG, x, t, d_prev, h, h_max, steps, first_dim, xn, d, hit, stats


# Outcomes of close_at_hit (mirrored in packings.workers.paths).
CH_CLOSED = 0  #: the projection onto every contact and hit pair counts, and its point is the endpoint's
CH_REJECTED = 1  #: close_pairs would return nothing, or an overlapping point: the caller walks to the contact
CH_PYTHON = 2  #: anything else (a near miss, a singular point, a near pair, more than one hit pair failing)


@numba.njit(**_JIT)
def _max_move(a, b):
    """packings.workers.paths.max_move: the largest displacement of a sphere between a and b (flat)."""
    out = 0.0
    for s in range(a.size // 3):
        d0 = a[3 * s] - b[3 * s]
        d1 = a[3 * s + 1] - b[3 * s + 1]
        d2 = a[3 * s + 2] - b[3 * s + 2]
        out = max(out, np.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
    return out


@numba.njit(**_JIT)
def close_at_hit(x, keep, pairs, hit, free, mask, upper, tol, dx_max, max_iter, guard, tol_a, tol_a0, round_off):
    """The common case of a path's endpoint (packings.workers.paths._endpoint) in one call:
    returns (status, point, its distances over ``upper``, every pair i < j).

    The first projection of packings.workers.paths.close_pairs: onto the contacts ``keep`` and the
    pairs ``pairs[hit]`` that stopped the path (in that order), polished, by the same Newton
    iteration (:func:`newton`); it counts if it converged and moved no sphere by more than
    ``tol_a0``.  CH_CLOSED when its point's contacts (pairs closer than 1 + ``tol_a``) are all
    constraints, no pair overlaps (closer than 1 - ``tol_a``), sum f^2 is at round-off (no
    refinement along flexes), and no pair of ``pairs`` other than a contact lies within 1 +
    ``tol_a0`` (packings.workers.paths.resolve_near_pairs has nothing to add): then the point and
    the contacts ``upper[d < 1 + tol_a]`` are the endpoint close_pairs returns and keeps.
    CH_REJECTED when close_pairs would return nothing (the projection does not count and there is
    one hit pair, so no subset to delete) or an overlapping point; CH_PYTHON otherwise, where the
    Python code decides from the start.
    """
    m = keep.shape[0]
    n3 = x.size
    n = n3 // 3
    e = 0
    for p in range(pairs.shape[0]):
        if hit[p]:
            e += 1
    cons = np.empty((m + e, 2), dtype=np.int64)
    for r in range(m):
        cons[r, 0] = keep[r, 0]
        cons[r, 1] = keep[r, 1]
    r = m
    for p in range(pairs.shape[0]):
        if hit[p]:
            cons[r, 0] = pairs[p, 0]
            cons[r, 1] = pairs[p, 1]
            r += 1
    xn, st, _, fsq, _, _ = newton(
        x, cons, free, mask, np.zeros((0, n3)), np.zeros(0), tol, dx_max, max_iter, True, guard
    )
    d = pair_distances_flat(xn, upper)
    if st != NEWTON_OK or not _max_move(xn, x) <= tol_a0:
        return (CH_REJECTED if e == 1 else CH_PYTHON), xn, d
    least = np.inf
    for p in range(d.size):
        least = min(least, d[p])
    if least < 1.0 - tol_a:
        return CH_REJECTED, xn, d
    constrained = np.zeros((n, n), dtype=np.bool_)  # the constraints as close_pairs's set of (i, j) has them
    for r in range(m + e):
        constrained[cons[r, 0], cons[r, 1]] = True
    for p in range(d.size):
        if d[p] < 1.0 + tol_a and not constrained[upper[p, 0], upper[p, 1]]:
            return CH_PYTHON, xn, d
    if not fsq <= round_off:
        return CH_PYTHON, xn, d
    for p in range(pairs.shape[0]):
        i = pairs[p, 0]
        j = pairs[p, 1]
        if i > j:
            i, j = j, i
        q = i * n - i * (i + 1) // 2 + (j - i - 1)  # the place of (i, j) in upper
        if d[q] < 1.0 + tol_a0 and not d[q] < 1.0 + tol_a:
            return CH_PYTHON, xn, d
    return CH_CLOSED, xn, d


@numba.njit(**_JIT)
def aligned_max_error(x, y):
    """max |x R - y| over coordinates for the orthogonal R (det = +-1) minimising ||x R - y|| (Procrustes)."""
    u, _, vt = np.linalg.svd(x.T @ y)
    return np.max(np.abs(x @ (u @ vt) - y))


@numba.njit(**_JIT)
def some_automorphism_aligns(ax, bx, adist, bdist, asorted, bsorted, autos, bound, tol_d):
    """Whether every |asorted - bsorted| is at most ``bound`` and, for some automorphism s (a row of
    ``autos``, in order), every |adist - bdist[s][:, s]| is at most ``bound`` and ``bx[s]`` aligns with
    ``ax`` within ``tol_d``."""
    for i in range(asorted.shape[0]):
        if abs(asorted[i] - bsorted[i]) > bound:
            return False
    k, n = autos.shape
    y = np.empty_like(bx)
    for g in range(k):
        s = autos[g]
        ok = True
        for i in range(n):
            for j in range(n):
                if abs(bdist[s[i], s[j]] - adist[i, j]) > bound:
                    ok = False
                    break
            if not ok:
                break
        if not ok:
            continue
        for i in range(n):
            y[i] = bx[s[i]]
        if aligned_max_error(ax, y) <= tol_d:
            return True
    return False


@numba.njit(**_JIT)
def floppy_without(coords, edges, spheres, triangles, guard):
    """For each sphere s = spheres[q] of the cluster ``coords`` (n x 3) with contacts ``edges``: the flexes of
    what is left without s, k - m > 0 (k = 3(n - 1) - 6 free coordinates, m its contacts), where the rank
    guard ``guard`` certifies that its pinned rigidity matrix has full row rank (:func:`regular_flexes`), in
    the frame of its contact triangle ``triangles[q]`` (its own labels: the spheres after s numbered one
    lower); -1 elsewhere (no flex left, or not certified).

    The frame is that of packings.workers.kernels.to_frame (a at the origin, b on +x, c in the xy-plane), in
    plain arithmetic, so its coordinates may differ from to_frame's in the last bits: a caller that must
    decide as the reference does passes a guard with room for that (packings.workers.kernels.floppy_without).
    """
    n = coords.shape[0]
    r = n - 1
    k = 3 * r - 6
    out = np.full(spheres.size, -1, dtype=np.int64)
    left = np.empty((edges.shape[0], 2), dtype=np.int64)
    x = np.empty(3 * r)
    mask = np.empty(3 * r)
    free = np.empty(k, dtype=np.int64)
    for q in range(spheres.size):
        s = spheres[q]
        m = 0
        for e in range(edges.shape[0]):
            i = edges[e, 0]
            j = edges[e, 1]
            if i != s and j != s:
                left[m, 0] = i - (i > s)
                left[m, 1] = j - (j > s)
                m += 1
        if m >= k:
            continue
        a = triangles[q, 0]
        b = triangles[q, 1]
        c = triangles[q, 2]
        pa = a + (a >= s)
        pb = b + (b >= s)
        pc = c + (c >= s)
        e1 = coords[pb] - coords[pa]
        e1 /= np.sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2])
        u = coords[pc] - coords[pa]
        e2 = u - (u[0] * e1[0] + u[1] * e1[1] + u[2] * e1[2]) * e1
        e2 /= np.sqrt(e2[0] * e2[0] + e2[1] * e2[1] + e2[2] * e2[2])
        e3 = np.array([e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]])
        for i in range(r):
            p = i + (i >= s)
            v0 = coords[p, 0] - coords[pa, 0]
            v1 = coords[p, 1] - coords[pa, 1]
            v2 = coords[p, 2] - coords[pa, 2]
            x[3 * i] = v0 * e1[0] + v1 * e1[1] + v2 * e1[2]
            x[3 * i + 1] = v0 * e2[0] + v1 * e2[1] + v2 * e2[2]
            x[3 * i + 2] = v0 * e3[0] + v1 * e3[1] + v2 * e3[2]
            mask[3 * i] = 1.0
            mask[3 * i + 1] = 1.0
            mask[3 * i + 2] = 1.0
        for p in (3 * a, 3 * a + 1, 3 * a + 2, 3 * b + 1, 3 * b + 2, 3 * c + 2):
            x[p] = 0.0
            mask[p] = 0.0
        f = 0
        for p in range(3 * r):
            if mask[p] == 1.0:
                free[f] = p
                f += 1
        if regular_flexes(x, left[:m], free, mask, guard) > 0:
            out[q] = k - m
    return out
