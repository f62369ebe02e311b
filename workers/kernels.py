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
  adding the six unit pinning rows of the paper: the right null space of the
  pinned matrix is the null space of the reduced one (zeros in the pinned
  coordinates), and the left null spaces (self-stresses) coincide because a
  self-stress exerts no net force or torque.

Backends
--------
Two implementations of the hot loop run behind this interface:

* ``"numba"`` (the default): compiled kernels in :mod:`packings.workers._compiled`.  Newton
  steps solve the normal equations by Cholesky, and the whole stepping loop of
  :func:`packings.workers.paths.follow_path` runs compiled.  It returns to Python at the
  endpoint, and at any point where a rank guard cannot prove that the pinned
  rigidity matrix has full row rank with every singular value at least
  ``GUARD_FACTOR * tol_n``: such steps (and the dimension test after a first
  step there) use the SVD of :func:`null_spaces`, exactly as the reference.
* ``"numpy"``: the plain numpy reference (least squares by SVD at every step,
  one Python iteration per step).

Select with :func:`set_backend` (process-wide), temporarily with the context
manager :func:`backend`, or for a whole process with the environment variable
``PACKINGS_KERNELS=numpy`` (read at import).  If numba cannot be imported the
numpy backend is used.  :func:`null_spaces` is the SVD in both backends.  Call
:func:`packings.workers.expand.warm_up` once per process to compile (or load from
numba's cache) every kernel before the first path.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import os
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
from scipy.linalg import orthogonal_procrustes

from packings.workers.cluster import cross3
from packings.workers.params import DEFAULT

BACKENDS = ("numba", "numpy")

#: The compiled path trusts the normal equations only where the smallest eigenvalue
#: of R_f R_f^T is provably at least (GUARD_FACTOR * tol_n)^2, i.e. every singular value
#: of R_f is at least GUARD_FACTOR * tol_n: far from the SVD's zero threshold tol_n.
GUARD_FACTOR = 100.0

#: packings.workers._compiled, imported when the compiled backend is first used (:func:`_numba`): importing
#: numba takes a quarter of a second, which a process that never follows a path (the coordinator,
#: the query commands) need not pay
_compiled = None


def numba_available() -> bool:
    """Whether numba is installed (a dependency; without it the numpy reference still runs)."""
    return _compiled is not None or importlib.util.find_spec("numba") is not None


def _numba():
    """:mod:`packings.workers._compiled`, imported on first use."""
    global _compiled
    if _compiled is None:
        from packings.workers import _compiled as module

        _compiled = module
    return _compiled


def _initial_backend() -> str:
    name = os.environ.get("PACKINGS_KERNELS", "").strip().lower() or "numba"
    if name not in BACKENDS:
        raise ValueError(f"PACKINGS_KERNELS must be one of {BACKENDS}, got {name!r}")
    if name == "numba" and not numba_available():  # pragma: no cover
        return "numpy"
    return name


_backend = _initial_backend()


def get_backend() -> str:
    """The backend in use: ``"numba"`` or ``"numpy"``."""
    return _backend


def set_backend(name: str) -> str:
    """Select the backend (``"numba"`` or ``"numpy"``) for this process; returns the previous one."""
    global _backend
    if name not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {name!r}")
    if name == "numba" and not numba_available():
        raise RuntimeError("numba is not available")
    previous, _backend = _backend, name
    return previous


@contextlib.contextmanager
def backend(name: str) -> Iterator[str]:
    """``with kernels.backend("numpy"): ...`` runs the block with that backend, then restores the previous one."""
    previous = set_backend(name)
    try:
        yield name
    finally:
        set_backend(previous)


def compiled() -> bool:
    """True when the compiled (numba) backend is selected."""
    return _backend == "numba"


def guard_threshold(tol_n: float) -> float:
    """Smallest eigenvalue of R_f R_f^T below which the compiled path defers to the SVD."""
    return (GUARD_FACTOR * tol_n) ** 2


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
    e3 = cross3(e1, e2)
    q = (p - p[a]) @ np.stack([e1, e2, e3], axis=1)
    q[a] = 0.0
    q[b, 1:] = 0.0
    q[c, 2] = 0.0
    return q.reshape(np.shape(x))


def residual(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """f_ij(x) = |x_i - x_j|^2 - 1 for every contact (i, j)."""
    if _backend == "numba":
        return _numba().residual(_f64(x), _i64(edges))
    return residual_numpy(x, edges)


def residual_numpy(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The numpy reference of :func:`residual`."""
    p = x.reshape(-1, 3)
    d = p[edges[:, 0]] - p[edges[:, 1]]
    return np.einsum("ij,ij->i", d, d) - 1.0


def as_kernel_array(a, dtype, shape: tuple[int, ...]) -> np.ndarray:
    """``a`` as a C-contiguous, writeable array of ``dtype`` and ``shape`` (a view when it already is one).

    Compiled kernels are specialised on these properties: passing read-only or
    strided arrays would compile (and cache) further variants of every kernel.
    """
    out = np.ascontiguousarray(a, dtype=dtype).reshape(shape)
    if not out.flags.writeable:
        out = out.copy()
    return out


def _f64(a: np.ndarray) -> np.ndarray:
    return as_kernel_array(a, np.float64, (-1,))


def _i64(a: np.ndarray) -> np.ndarray:
    return as_kernel_array(a, np.int64, (-1, 2))


def rigidity_matrix(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """R(x): row k = (i, j) has x_i - x_j in sphere i's columns and x_j - x_i in j's.

    It is half the Jacobian of the residuals, and (R(p) y)_k = (p_i - p_j).(y_i - y_j).
    """
    if _backend == "numba":
        return _numba().rigidity_matrix(_f64(x), _i64(edges))
    return rigidity_matrix_numpy(x, edges)


def rigidity_matrix_numpy(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The numpy reference of :func:`rigidity_matrix`."""
    p = x.reshape(-1, 3)
    m = edges.shape[0]
    r = np.zeros((m, p.shape[0], 3))
    d = p[edges[:, 0]] - p[edges[:, 1]]
    rows = np.arange(m)
    r[rows, edges[:, 0]] = d
    r[rows, edges[:, 1]] = -d
    return r.reshape(m, 3 * p.shape[0])


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
    stall: int = 0,
    tol_n: float | None = None,
) -> Projection:
    """Newton's method for f(x) = 0 with the pinned coordinates held fixed.

    Each step is the minimum-norm least-squares solution of J dx = -f (J = 2R on
    the free columns), scaled down to length ``dx_max`` if longer.  Converged
    when sum f^2 < tol.  ``extra = (A, b)`` appends the linear equations
    A x[free] = b (used by the dimension test).  Never returns ok=True for a
    point that does not satisfy the tolerance.  With ``stall`` > 0 the iteration
    gives up (ok=False) as soon as sum f^2 has not gone below its smallest value
    so far for ``stall`` consecutive iterations (used by the dimension test's
    probes, :func:`packings.workers.dimension.solution_dimension`); 0 never gives up early.

    With ``polish`` (used for clusters that are kept), iteration goes on after
    convergence for as long as each step at least halves sum f^2, so that the
    coordinates are as accurate as float64 and the conditioning allow: at a
    regular point Newton then reaches round-off; near a singular point, where it
    converges only linearly, the coordinates end accurate to about sqrt(|f|).

    With the numba backend the same iteration runs compiled; each step solves the
    normal equations (J J^T) y = -f, dx = J^T y by Cholesky, which is the same
    minimum-norm step while J has full row rank, and falls back to the least-squares
    solve where the rank guard (:func:`guard_threshold` of ``tol_n``, by default
    the paper's 1e-6) fails.  The numpy backend ignores ``tol_n``.
    """
    if _backend == "numba":
        return project_compiled(
            x0,
            edges,
            free,
            tol=tol,
            dx_max=dx_max,
            max_iter=max_iter,
            extra=extra,
            polish=polish,
            stall=stall,
            tol_n=tol_n,
        )
    return project_numpy(
        x0, edges, free, tol=tol, dx_max=dx_max, max_iter=max_iter, extra=extra, polish=polish, stall=stall
    )


def free_mask(n3: int, free: np.ndarray) -> np.ndarray:
    """1.0 on the free coordinates, 0.0 on the pinned ones (length 3n)."""
    mask = np.zeros(n3)
    mask[free] = 1.0
    return mask


def project_compiled(
    x0: np.ndarray,
    edges: np.ndarray,
    free: np.ndarray,
    *,
    tol: float,
    dx_max: float,
    max_iter: int,
    extra: tuple[np.ndarray, np.ndarray] | None = None,
    polish: bool = False,
    stall: int = 0,
    tol_n: float | None = None,
) -> Projection:
    """:func:`project` by the compiled kernel (normal equations, least squares where the guard fails)."""
    x = _f64(x0)
    free = as_kernel_array(free, np.int64, (-1,))
    if extra is None:
        a = np.zeros((0, x.size))
        b = np.zeros(0)
    else:
        ea = np.atleast_2d(np.asarray(extra[0], dtype=np.float64))
        a = np.zeros((ea.shape[0], x.size))
        a[:, free] = ea
        b = as_kernel_array(extra[1], np.float64, (-1,))
    g = guard_threshold(DEFAULT.tol_n if tol_n is None else tol_n)
    compiled = _numba()
    xn, status, it, fsq, _, _ = compiled.newton(
        x,
        _i64(edges),
        free,
        free_mask(x.size, free),
        a,
        b,
        float(tol),
        float(dx_max),
        int(max_iter),
        bool(polish),
        float(g),
        int(stall),
    )
    return Projection(xn, status == compiled.NEWTON_OK, int(it), float(fsq))


def project_numpy(
    x0: np.ndarray,
    edges: np.ndarray,
    free: np.ndarray,
    *,
    tol: float,
    dx_max: float,
    max_iter: int,
    extra: tuple[np.ndarray, np.ndarray] | None = None,
    polish: bool = False,
    stall: int = 0,
) -> Projection:
    """The numpy reference of :func:`project`: a least-squares (SVD) solve at every step."""
    x = np.array(x0, dtype=np.float64, copy=True)
    fsq = np.inf
    converged = False
    best_x, best_fsq = x.copy(), np.inf
    low, since = np.inf, 0
    for it in range(max_iter + 1):
        f = residual_numpy(x, edges)
        if extra is not None:
            f = np.concatenate([f, extra[0] @ x[free] - extra[1]])
        fsq = float(f @ f)
        if not np.isfinite(fsq):
            break
        if converged:
            if fsq > 0.5 * best_fsq:
                return Projection(best_x, True, it, best_fsq)
            best_x, best_fsq = x.copy(), fsq
            if fsq == 0.0:  # exact: every further step is zero
                return Projection(best_x, True, it, fsq)
        elif fsq < tol:
            if not polish or fsq == 0.0:
                return Projection(x, True, it, fsq)
            converged = True
            best_x, best_fsq = x.copy(), fsq
        elif stall > 0:
            if fsq < low:
                low, since = fsq, 0
            else:
                since += 1
                if since >= stall:
                    return Projection(x, False, it, fsq)
        if it == max_iter:
            break
        j = 2.0 * rigidity_matrix_numpy(x, edges)[:, free]
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


def refine_singular(x: np.ndarray, edges: np.ndarray, free: np.ndarray, max_iter: int = 200) -> np.ndarray:
    """x moved to where E = sum_k f_k^2 is smallest: Newton's method on E along the flexes, each step
    followed by Gauss-Newton steps back onto the valley floor of E.

    At a singular solution (a flex held by a stress) the least-squares Newton step of
    :func:`project` is orthogonal to the flexes, so it cannot correct an error along them: the
    part of f it cannot reduce is of second order in that error, and a polished singular point
    keeps coordinates accurate only to about sqrt(|f| / margin), which can exceed tol_d (one
    cluster then stored twice).  Along the flexes E is a flat quartic at the bottom of a curved
    valley whose walls rise like R^T R, so each iteration

    1. takes the Newton step of E with its full Hessian R^T R + sum_k f_k grad^2 f_k (each
       grad^2 f_k a constant Laplacian block) written in the basis of J's right singular vectors
       and scaled to unit diagonal (:func:`_newton_step_of_e`), so that the small curvature along
       a flex is resolved relative to itself, not to |R|^2;
    2. returns to the floor of the valley by Gauss-Newton steps on J's regular singular values
       only (:func:`_onto_the_valley_floor`), which a curved valley needs: without them E rises
       along the step's straight line and the step is halved to nothing;

    halving the step (at most ten times) until E decreases, and ending when no halving does.
    Along the flexes this converges linearly (the error two thirds of itself per step), down to
    about sqrt(1e-15 / margin), where E reaches round-off.  Numpy only: it runs for the few
    singular endpoints.
    """
    x = np.array(x, dtype=np.float64, copy=True)
    f = residual_numpy(x, edges)
    e0 = float(f @ f)
    for _ in range(max_iter):
        if e0 == 0.0:
            break
        dx = _newton_step_of_e(x, f, edges, free)
        t = 1.0
        while t > 1e-3:
            y = x.copy()
            y[free] += t * dx
            y = _onto_the_valley_floor(y, edges, free)
            fy = residual_numpy(y, edges)
            ey = float(fy @ fy)
            if ey < e0:
                break
            t /= 2
        else:
            break
        x, f, e0 = y, fy, ey
    return x


def _newton_step_of_e(x: np.ndarray, f: np.ndarray, edges: np.ndarray, free: np.ndarray) -> np.ndarray:
    """The Newton step dx (on the free coordinates) of E = |f|^2, with |H|'s eigenvalues (round-off ones
    left out); H in the basis of J's right singular vectors (the flexes last), scaled to unit diagonal."""
    n = x.size // 3
    j = 2.0 * rigidity_matrix_numpy(x, edges)[:, free]
    v = np.linalg.svd(j)[2].T
    jv = j @ v
    lap = np.zeros((n, n))
    np.add.at(lap, (edges[:, 0], edges[:, 0]), f)
    np.add.at(lap, (edges[:, 1], edges[:, 1]), f)
    np.add.at(lap, (edges[:, 0], edges[:, 1]), -f)
    np.add.at(lap, (edges[:, 1], edges[:, 0]), -f)
    h = jv.T @ jv + 2.0 * v.T @ np.kron(lap, np.eye(3))[np.ix_(free, free)] @ v
    d = np.sqrt(np.abs(np.diag(h)))
    d = 1.0 / np.where(d > 0.0, d, 1.0)
    w, u = np.linalg.eigh(d[:, None] * h * d[None, :])
    w = np.abs(w)
    w[w < 1e-15 * w.max()] = np.inf
    return -v @ (d * (u @ ((u.T @ (d * (jv.T @ f))) / w)))


#: singular values of J below this fraction of the largest count as flexes in :func:`_onto_the_valley_floor`
_FLEX_RATIO = 1e-3


def _onto_the_valley_floor(x: np.ndarray, edges: np.ndarray, free: np.ndarray, steps: int = 4) -> np.ndarray:
    """x after Gauss-Newton steps that leave the flexes alone: the least-squares step on J's singular
    values above ``_FLEX_RATIO`` of the largest only (a step along a flex is f's stress part divided
    by a tiny singular value, which is what keeps plain Gauss-Newton from converging there)."""
    x = x.copy()
    for _ in range(steps):
        f = residual_numpy(x, edges)
        u, s, vt = np.linalg.svd(2.0 * rigidity_matrix_numpy(x, edges)[:, free], full_matrices=False)
        keep = s > _FLEX_RATIO * s[0]
        dx = vt[keep].T @ ((u[:, keep].T @ f) / s[keep])
        x[free] -= dx
        if np.abs(dx).max() < 1e-8:  # Gauss-Newton converges quadratically: a further step would be round-off
            break
    return x


def regular_flexes(x: np.ndarray, edges: np.ndarray, free: np.ndarray, tol_n: float) -> int | None:
    """dim V when a cheap test certifies that R[:, free] has full row rank, else None.

    Certified (compiled backend only) means the Cholesky factor of R_f R_f^T
    proves its smallest eigenvalue is at least :func:`guard_threshold` (tol_n):
    then :func:`null_spaces` would find rank m, no self-stress (W empty) and
    dim V = len(free) - m, so callers that need only those sizes may skip the
    SVD.  Returns None whenever that is not certified, and always with the
    numpy backend (the reference takes the SVD).
    """
    if _backend != "numba":
        return None
    x = _f64(x)
    free = as_kernel_array(free, np.int64, (-1,))
    a = _numba().regular_flexes(x, _i64(edges), free, free_mask(x.size, free), guard_threshold(tol_n))
    return None if a < 0 else int(a)


#: :func:`floppy_without` certifies with this many times the rank guard, so that what it certifies in its
#: own arithmetic of the frame, the guard certifies in :func:`to_frame`'s (the two differ in the last bits)
FLOPPY_GUARD_ROOM = 4.0


def floppy_without(
    coords: np.ndarray, edges: np.ndarray, spheres: np.ndarray, triangles: np.ndarray, tol_n: float
) -> np.ndarray:
    """For each sphere s of ``spheres``: the flexes (> 0) of the cluster ``coords`` (n x 3, contacts ``edges``)
    without s where :func:`regular_flexes` would certify them, pinned by its contact triangle ``triangles[q]``
    (in its own labels: the spheres after s one lower) after :func:`to_frame`; -1 where that is not certain
    (no flex left, or the rank not certified with room to spare, :data:`FLOPPY_GUARD_ROOM`).  Always -1 with
    the numpy backend (the reference takes the SVD, as :func:`regular_flexes`)."""
    spheres = as_kernel_array(spheres, np.int64, (-1,))
    if _backend != "numba":
        return np.full(spheres.size, -1, dtype=np.int64)
    return _numba().floppy_without(
        _f64(coords).reshape(-1, 3),
        _i64(edges),
        spheres,
        as_kernel_array(triangles, np.int64, (-1, 3)),
        FLOPPY_GUARD_ROOM * guard_threshold(tol_n),
    )


@dataclass(frozen=True)
class NullSpaces:
    """Singular values of R[:, free], its right null space V and left null space W.

    V is returned in full coordinates (3n x a, zeros in pinned coordinates);
    W is m x b.  Columns are orthonormal.  ``pinv`` is the pseudo-inverse of
    R[:, free] on the singular values counted nonzero, in full coordinates
    (3n x m, zero rows at the pinned coordinates), from the same SVD when first
    asked for; None without it.
    """

    sigma: np.ndarray
    V: np.ndarray
    W: np.ndarray
    svd: tuple | None = field(default=None, repr=False, compare=False)  #: (u, vt, rank, free) of that SVD

    @functools.cached_property
    def pinv(self) -> np.ndarray | None:
        if self.svd is None:
            return None
        u, vt, rank, free = self.svd
        out = np.zeros((self.V.shape[0], u.shape[0]))
        out[free] = vt[:rank].T @ (u[:, :rank].T / self.sigma[:rank, None])
        return out


def null_spaces(x: np.ndarray, edges: np.ndarray, free: np.ndarray, tol_n: float) -> NullSpaces:
    """V and W of the pinned rigidity matrix, by SVD, singular values < tol_n counted as zero."""
    r = rigidity_matrix_numpy(x, edges)[:, free]
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
    return NullSpaces(s, v, u[:, rank:], (u, vt, rank, free))


def pair_distances_flat(x: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """|x_i - x_j| for each (i, j) in ``pairs``."""
    if _backend == "numba":
        return _numba().pair_distances_flat(_f64(x), _i64(pairs))
    p = x.reshape(-1, 3)
    d = p[pairs[:, 0]] - p[pairs[:, 1]]
    return np.sqrt(np.einsum("ij,ij->i", d, d))


def some_automorphism_aligns(
    ax: np.ndarray,
    bx: np.ndarray,
    adist: np.ndarray,
    bdist: np.ndarray,
    asorted: np.ndarray,
    bsorted: np.ndarray,
    autos: np.ndarray,
    bound: float,
    tol_d: float,
) -> bool:
    """Whether two clusters in canonical order are the same geometry under some automorphism.

    ``ax``, ``bx``: centred coordinates (n x 3); ``adist``, ``bdist``: their pair-distance matrices;
    ``asorted``, ``bsorted``: their pair distances sorted (a rejection that needs no labelling);
    ``autos``: the automorphism group of their (common) canonical contact graph, one permutation a
    row.  True iff every |asorted - bsorted| is at most ``bound`` and for some ``s`` (tried in order)
    every |adist - bdist[s][:, s]| is at most ``bound`` and ``bx[s]`` is within ``tol_d`` of ``ax`` in
    every coordinate after the optimal orthogonal alignment (:func:`aligned_max_error`).
    """
    if _backend == "numba":
        return bool(_numba().some_automorphism_aligns(ax, bx, adist, bdist, asorted, bsorted, autos, bound, tol_d))
    if np.max(np.abs(asorted - bsorted), initial=0.0) > bound:
        return False
    relabelled = bdist[autos[:, :, None], autos[:, None, :]]
    passing = np.flatnonzero(np.abs(relabelled - adist).max(axis=(1, 2), initial=0.0) <= bound)
    return any(aligned_max_error(ax, bx[autos[k]]) <= tol_d for k in passing)


def aligned_max_error(x: np.ndarray, y: np.ndarray) -> float:
    """max |x R - y| over coordinates for the orthogonal R (det = +-1) that minimises the Frobenius
    norm ||x R - y|| (both already centred): the orthogonal Procrustes problem (R = U V^T from the SVD
    x^T y = U S V^T), solved by scipy."""
    r, _ = orthogonal_procrustes(x, y, check_finite=False)
    return float(np.max(np.abs(x @ r - y)))
