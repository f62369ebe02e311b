"""The hot loop of the method, behind a narrow interface.

Everything that runs at every step of a path lives here: the contact residuals,
the rigidity matrix, Newton projection, null spaces and the pair-distance check.
The rest of ``workers`` calls only these functions, so a compiled implementation
can replace this module without touching the algorithms around it.

Conventions
-----------
* ``x`` is a flat float64 vector of length 3n (sphere i at ``x[3i:3i+3]``).
* ``edges`` is an (m x 2) int64 array of contacts (i, j).
* ``free`` is the int64 array of coordinates that may move.  Rigid motions are
  removed by pinning a triangle (a, b, c) placed with a at the origin, b on the
  x-axis and c in the xy-plane: the six coordinates x_a, y_a, z_a, y_b, z_b, z_c
  are fixed.  Dropping their columns from the rigidity matrix is the same as
  adding the six unit pinning rows of METHOD.md: the right null space of the
  pinned matrix is the null space of the reduced one (zeros in the pinned
  coordinates), and the left null spaces (self-stresses) coincide because a
  self-stress exerts no net force or torque.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def pinned_coordinates(tri: tuple[int, int, int]) -> np.ndarray:
    """Indices of the six pinned coordinates for the triangle (a, b, c)."""
    a, b, c = tri
    return np.array([3 * a, 3 * a + 1, 3 * a + 2, 3 * b + 1, 3 * b + 2, 3 * c + 2], dtype=np.int64)


def free_coordinates(n: int, tri: tuple[int, int, int]) -> np.ndarray:
    """Indices of the 3n - 6 coordinates left free by pinning the triangle."""
    mask = np.ones(3 * n, dtype=bool)
    mask[pinned_coordinates(tri)] = False
    return np.nonzero(mask)[0]


def to_frame(x: np.ndarray, tri: tuple[int, int, int]) -> np.ndarray:
    """Rigidly move the cluster so that a is at the origin, b on +x, c in the xy-plane (y > 0).

    ``x`` may be n x 3 or flat; the result has the same shape.  A proper rotation
    (no reflection) is used.
    """
    p = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    a, b, c = tri
    e1 = p[b] - p[a]
    e1 /= np.linalg.norm(e1)
    u = p[c] - p[a]
    e2 = u - (u @ e1) * e1
    e2 /= np.linalg.norm(e2)
    e3 = np.cross(e1, e2)
    q = (p - p[a]) @ np.stack([e1, e2, e3], axis=1)
    q[a] = 0.0
    q[b, 1:] = 0.0
    q[c, 2] = 0.0
    return q.reshape(np.shape(x))


def residual(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """f_ij(x) = |x_i - x_j|^2 - 1 for every contact (i, j)."""
    p = x.reshape(-1, 3)
    d = p[edges[:, 0]] - p[edges[:, 1]]
    return np.einsum("ij,ij->i", d, d) - 1.0


def rigidity_matrix(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """R(x): row k = (i, j) has x_i - x_j in sphere i's columns and x_j - x_i in j's.

    It is half the Jacobian of the residuals, and (R(p) y)_k = (p_i - p_j).(y_i - y_j).
    """
    p = x.reshape(-1, 3)
    m = edges.shape[0]
    r = np.zeros((m, p.shape[0], 3))
    d = p[edges[:, 0]] - p[edges[:, 1]]
    rows = np.arange(m)
    r[rows, edges[:, 0]] = d
    r[rows, edges[:, 1]] = -d
    return r.reshape(m, -1)


@dataclass(frozen=True)
class Projection:
    """Result of a Newton projection onto the constraint set."""

    x: np.ndarray
    ok: bool
    iterations: int
    residual: float  #: sum of squared constraint residuals at x


def project(
    x0: np.ndarray,
    edges: np.ndarray,
    free: np.ndarray,
    *,
    tol: float,
    dx_max: float,
    max_iter: int,
    extra: tuple[np.ndarray, np.ndarray] | None = None,
    polish: bool = False,
) -> Projection:
    """Newton's method for f(x) = 0 with the pinned coordinates held fixed.

    Each step is the minimum-norm least-squares solution of J dx = -f (J = 2R on
    the free columns), scaled down to length ``dx_max`` if longer.  Converged
    when sum f^2 < tol.  ``extra = (A, b)`` appends the linear equations
    A x[free] = b (used by the dimension test).  Never returns ok=True for a
    point that does not satisfy the tolerance.

    With ``polish`` (used for clusters that are kept), iteration goes on after
    convergence for as long as each step at least halves sum f^2, so that the
    coordinates are as accurate as float64 and the conditioning allow: at a
    regular point Newton then reaches round-off; near a singular point, where it
    converges only linearly, the coordinates end accurate to about sqrt(|f|).
    """
    x = np.array(x0, dtype=np.float64, copy=True)
    fsq = np.inf
    converged = False
    best_x, best_fsq = x.copy(), np.inf
    for it in range(max_iter + 1):
        f = residual(x, edges)
        if extra is not None:
            f = np.concatenate([f, extra[0] @ x[free] - extra[1]])
        fsq = float(f @ f)
        if not np.isfinite(fsq):
            break
        if converged:
            if fsq > 0.5 * best_fsq:
                return Projection(best_x, True, it, best_fsq)
            best_x, best_fsq = x.copy(), fsq
        elif fsq < tol:
            if not polish or fsq == 0.0:
                return Projection(x, True, it, fsq)
            converged = True
            best_x, best_fsq = x.copy(), fsq
        if it == max_iter:
            break
        j = 2.0 * rigidity_matrix(x, edges)[:, free]
        if extra is not None:
            j = np.vstack([j, extra[0]])
        dx = np.linalg.lstsq(j, -f, rcond=None)[0]
        step = np.linalg.norm(dx)
        if step > dx_max:
            dx *= dx_max / step
        x[free] += dx
    if converged:
        return Projection(best_x, True, max_iter, best_fsq)
    return Projection(x, False, max_iter, fsq)


@dataclass(frozen=True)
class NullSpaces:
    """Singular values of R[:, free], its right null space V and left null space W.

    V is returned in full coordinates (3n x a, zeros in pinned coordinates);
    W is m x b.  Columns are orthonormal.
    """

    sigma: np.ndarray
    V: np.ndarray
    W: np.ndarray


def null_spaces(x: np.ndarray, edges: np.ndarray, free: np.ndarray, tol_n: float) -> NullSpaces:
    """V and W of the pinned rigidity matrix, by SVD, singular values < tol_n counted as zero."""
    r = rigidity_matrix(x, edges)[:, free]
    m, k = r.shape
    if m == 0:
        v = np.zeros((x.size, k))
        v[free, np.arange(k)] = 1.0
        return NullSpaces(np.zeros(0), v, np.zeros((0, 0)))
    u, s, vt = np.linalg.svd(r, full_matrices=True)
    rank = int(np.count_nonzero(s >= tol_n))
    vf = vt[rank:].T
    v = np.zeros((x.size, vf.shape[1]))
    v[free] = vf
    return NullSpaces(s, v, u[:, rank:])


def pair_distances_flat(x: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """|x_i - x_j| for each (i, j) in ``pairs``."""
    p = x.reshape(-1, 3)
    d = p[pairs[:, 0]] - p[pairs[:, 1]]
    return np.sqrt(np.einsum("ij,ij->i", d, d))
