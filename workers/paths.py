"""Following a one-dimensional path from a rigid cluster to its next rigid cluster (METHOD.md)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import combinations

import numpy as np

from workers import kernels
from workers.cluster import contacts_from_coords, pair_distances
from workers.dimension import solution_dimension
from workers.outcomes import (  # noqa: F401 - the outcomes of a path, named here too
    DIMENSION_CHANGED,
    FLOPPY,
    OVERLAP,
    PROJECTION_FAILED,
    RIGID,
    SHORTENS,
    TOO_LONG,
    UNDECIDED_END,
)
from workers.params import Params
from workers.rigidity import UNDECIDED, Rigidity, rigidity_from_null_spaces, rigidity_without_stress

try:  # numba is a dependency; without it (or with a broken install) the reference still runs
    from workers import _compiled
except ImportError:  # pragma: no cover
    _compiled = None


@dataclass(frozen=True)
class PathEnd:
    """Where a path ended.  ``coords`` and ``contacts`` are set when an endpoint was projected."""

    outcome: str
    steps: int
    coords: np.ndarray | None = None
    contacts: tuple[tuple[int, int], ...] | None = None
    rigidity: Rigidity | None = None
    new_contacts: tuple[tuple[int, int], ...] = ()
    first_step_dim: int | None = None  #: dimension of the set after the first step (None: no step taken)


def non_contact_pairs(n: int, edges: np.ndarray) -> np.ndarray:
    """All pairs (i < j) that are not in ``edges``, as a (k x 2) array."""
    mask = np.triu(np.ones((n, n), dtype=bool), k=1)
    mask[edges[:, 0], edges[:, 1]] = False
    mask[edges[:, 1], edges[:, 0]] = False
    i, j = np.nonzero(mask)
    return np.stack([i, j], axis=1).astype(np.int64)


def follow_path(
    x: np.ndarray,
    keep: np.ndarray,
    broken: np.ndarray,
    tangent: np.ndarray,
    free: np.ndarray,
    params: Params,
) -> PathEnd:
    """Follow the path of {f_keep = 0} from x along ``tangent`` until a new contact forms.

    Predictor step of length h along the tangent, Newton projection, new tangent
    = the previous one projected (least squares) onto the null space of R at the
    new point.  The first step is ds, so that the dimension re-check after it
    looks at the solution set near the start (from a singular cluster a large
    first step lands on whatever surrounds a singular path); the step then
    doubles up to ds0, until a non-contact pair that is approaching comes
    within 1 + tol_a0; then the step is redone with ds (endgame), halving it
    whenever a pair would overlap by more than tol_a0, until an approaching pair
    is within 1 + tol_a0 of contact.  The new contacts are then added and the
    point projected; if that fails, subsets of the new contacts are deleted
    until it succeeds.

    The dimension is re-checked after the first step and recorded in the result.
    If it is 0 the path stops.  If it is more than 1 the path stops when
    ``params.stop_on_dimension_change`` is set (METHOD.md's rule); otherwise it
    goes on, carrying the tangent by least squares as at any singular point.
    Going on cannot produce a false cluster, since every endpoint is kept only
    if it passes the rigidity test; it reaches the rigid clusters that lie at the
    end of a singular path which a finite first step leaves (a thin set of
    dimension 2 surrounds such a path).
    """
    if kernels.compiled():
        return _follow_compiled(x, keep, broken, tangent, free, params)
    return _follow_numpy(x, keep, broken, tangent, free, params)


def _broken_pairs(n: int, keep: np.ndarray, broken: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The non-contact pairs of ``keep`` and the indices among them of the broken contacts."""
    pairs = non_contact_pairs(n, keep)
    broken = np.asarray(broken, dtype=np.int64).reshape(-1, 2)
    is_broken = np.zeros((n, n), dtype=bool)
    is_broken[broken[:, 0], broken[:, 1]] = True
    broken_idx = np.nonzero(is_broken[pairs[:, 0], pairs[:, 1]])[0].astype(np.int64)
    return pairs, broken_idx


def _svd_tangent(xn, keep, free, t, params: Params, first: bool) -> tuple[np.ndarray | None, int | None]:
    """The next tangent at xn by the SVD: ``t`` projected onto the null space V of R(xn).

    On the first step the dimension is re-checked (solution_dimension) and, when
    it is 1, V is its tangent basis.  Returns (new tangent or None if the path
    must stop with DIMENSION_CHANGED, the first-step dimension or None).
    """
    ns = kernels.null_spaces(xn, keep, free, params.tol_n)
    V = ns.V
    first_dim = None
    if first:
        dim = solution_dimension(xn, keep, free, params, ns, limit=1)
        first_dim = dim.dim
        if dim.dim == 0 or (dim.dim > 1 and params.stop_on_dimension_change):
            return None, first_dim
        if dim.dim == 1:
            V = dim.tangents
    if V.shape[1] == 0:
        return None, first_dim
    tn = V @ (V.T @ t)
    norm = np.linalg.norm(tn)
    if norm < 1e-8:
        return None, first_dim
    return tn / norm, first_dim


def _follow_numpy(x, keep, broken, tangent, free, params: Params) -> PathEnd:
    """The reference loop of :func:`follow_path`: one Python iteration per step, an SVD at every step."""
    n = x.size // 3
    kw = dict(tol=params.tol, dx_max=params.dx_max, max_iter=params.newton_max_iter, tol_n=params.tol_n)
    pairs, broken_idx = _broken_pairs(n, keep, broken)
    d_prev = kernels.pair_distances_flat(x, pairs)
    t = tangent / np.linalg.norm(tangent)
    h_max = params.ds0
    h = min(params.ds, h_max)
    h_min = params.ds / 1024
    first_dim: int | None = None  # set after the first step is taken
    steps = 0

    def end(outcome: str, n_steps: int) -> PathEnd:
        return PathEnd(outcome, n_steps, first_step_dim=first_dim)

    while steps < params.max_path_steps:
        pr = kernels.project(x + h * t, keep, free, **kw)
        if not pr.ok or (pr.x - x) @ t <= 0.0:
            h /= 2
            if h < h_min:
                return end(PROJECTION_FAILED, steps)
            continue
        xn = pr.x
        d = kernels.pair_distances_flat(xn, pairs)
        if first_dim is None and broken_idx.size and (d[broken_idx] <= d_prev[broken_idx]).any():
            return end(SHORTENS, steps)
        hit = (d < d_prev) & (d < 1.0 + params.tol_a0)
        if hit.any():
            if h_max > params.ds:  # back up and approach with the small step
                h_max = params.ds
                h = min(h, h_max)
                continue
            if (d[hit] < 1.0 - params.tol_a0).any():
                h /= 2
                if h < h_min:
                    return end(PROJECTION_FAILED, steps)
                continue
            return replace(_endpoint(xn, keep, pairs[hit], free, params, steps + 1), first_step_dim=first_dim)
        tn, dim = _svd_tangent(xn, keep, free, t, params, first_dim is None)
        if first_dim is None:
            first_dim = dim
        if tn is None:
            return end(DIMENSION_CHANGED, steps + 1)
        t = tn
        x, d_prev = xn, d
        steps += 1
        h = min(2 * h, h_max)
    return end(TOO_LONG, steps)


#: Path outcomes by the status codes of the compiled loop.
_COMPILED_OUTCOMES = {
    _compiled.ST_PROJECTION_FAILED: PROJECTION_FAILED,
    _compiled.ST_SHORTENS: SHORTENS,
    _compiled.ST_DIMENSION_CHANGED: DIMENSION_CHANGED,
    _compiled.ST_TOO_LONG: TOO_LONG,
} if _compiled is not None else {}


def _follow_compiled(x, keep, broken, tangent, free, params: Params) -> PathEnd:
    """:func:`follow_path` with the stepping loop compiled (workers._compiled.follow_steps).

    The compiled loop runs the same steps as :func:`_follow_numpy` and returns
    here only to end the path or when its rank guard cannot certify that R(xn)
    has full row rank (so that the null space is the complement of the row
    space, and after the first step the dimension is the reference's "regular"
    |V|).  Those steps take their tangent, and on the first step the dimension,
    from the SVD (:func:`_svd_tangent`) exactly as the reference does, and the
    compiled loop then resumes.
    """
    n = x.size // 3
    x = kernels.as_kernel_array(x, np.float64, (-1,))
    keep = kernels.as_kernel_array(keep, np.int64, (-1, 2))
    free = kernels.as_kernel_array(free, np.int64, (-1,))
    pairs, broken_idx = _broken_pairs(n, keep, broken)
    mask = kernels.free_mask(x.size, free)
    d_prev = kernels.pair_distances_flat(x, pairs)
    t = kernels.as_kernel_array(tangent / np.linalg.norm(tangent), np.float64, (-1,))
    h_max = float(params.ds0)
    h = min(params.ds, h_max)
    h_min = params.ds / 1024
    guard = kernels.guard_threshold(params.tol_n)
    first_dim: int | None = None
    steps = 0
    while True:
        status, x, t, d_prev, h, h_max, steps, dim, xn, d, hit, _ = _compiled.follow_steps(
            x, t, d_prev, h, h_max, steps, first_dim is None, keep, free, mask, pairs, broken_idx,
            params.ds, h_min, params.tol, params.dx_max, params.newton_max_iter, params.tol_a0,
            params.max_path_steps, guard, params.stop_on_dimension_change,
        )  # fmt: skip
        if dim >= 0:
            first_dim = int(dim)
        if status == _compiled.ST_HIT:
            return replace(_endpoint(xn, keep, pairs[hit], free, params, steps + 1), first_step_dim=first_dim)
        if status != _compiled.ST_NEED_SVD:
            return PathEnd(_COMPILED_OUTCOMES[status], steps, first_step_dim=first_dim)
        tn, dim = _svd_tangent(xn, keep, free, t, params, first_dim is None)
        if first_dim is None:
            first_dim = dim
        if tn is None:
            return PathEnd(DIMENSION_CHANGED, steps + 1, first_step_dim=first_dim)
        t = kernels.as_kernel_array(tn, np.float64, (-1,))
        x, d_prev = xn, d
        steps += 1
        h = min(2 * h, h_max)
        if steps >= params.max_path_steps:
            return PathEnd(TOO_LONG, steps, first_step_dim=first_dim)


def _endpoint(x, keep, new, free, params: Params, steps: int) -> PathEnd:
    """Add the new contacts, project, and classify the endpoint."""
    kw = dict(tol=params.tol, dx_max=params.dx_max, max_iter=params.newton_max_iter, tol_n=params.tol_n)
    new_t = tuple((int(i), int(j)) for i, j in new)
    pr = None
    for r in range(0, len(new)):
        for drop in combinations(range(len(new)), r):
            sel = np.array([k for k in range(len(new)) if k not in drop], dtype=np.int64)
            edges = np.vstack([keep, new[sel]])
            pr = kernels.project(x, edges, free, polish=True, **kw)
            if pr.ok:
                break
        if pr is not None and pr.ok:
            break
    if pr is None or not pr.ok:
        return PathEnd(PROJECTION_FAILED, steps, new_contacts=new_t)
    coords = pr.x.reshape(-1, 3)
    contacts = contacts_from_coords(coords, params.tol_a)
    constrained = {(int(i), int(j)) for i, j in edges}
    for _ in range(3):
        if set(contacts) <= constrained:
            break
        # A pair within tol_a of touching that was not a constraint: a contact of the endpoint must hold
        # to the Newton tolerance like every other, so project again with all of them.  Where no such
        # point exists (the pair passes within tol_a of touching and the path goes on) the endpoint is
        # not a cluster: without this, each such near miss was stored as a "rigid" cluster, a new copy
        # for each path that passed by (n = 12: one contact graph with 74 such geometries).
        edges = np.array(contacts, dtype=np.int64)
        pr = kernels.project(pr.x, edges, free, polish=True, **kw)
        if not pr.ok:
            return PathEnd(PROJECTION_FAILED, steps, new_contacts=new_t)
        constrained = set(contacts)
        coords = pr.x.reshape(-1, 3)
        contacts = contacts_from_coords(coords, params.tol_a)
    else:
        return PathEnd(PROJECTION_FAILED, steps, new_contacts=new_t)
    dist = pair_distances(coords)
    np.fill_diagonal(dist, np.inf)
    if dist.min() < 1.0 - params.tol_a:
        return PathEnd(OVERLAP, steps, coords, contacts, new_contacts=new_t)
    edges = np.array(contacts, dtype=np.int64)
    flexes = kernels.regular_flexes(pr.x, edges, free, params.tol_n)
    if flexes is not None:  # certified full row rank: what the SVD would find, without it
        rig = rigidity_without_stress(flexes)
    else:
        rig = rigidity_from_null_spaces(kernels.null_spaces(pr.x, edges, free, params.tol_n), edges, params)
    outcome = RIGID if rig.rigid else (UNDECIDED_END if rig.kind == UNDECIDED else FLOPPY)
    return PathEnd(outcome, steps, coords, contacts, rig, new_t)
