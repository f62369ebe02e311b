"""Following a one-dimensional path from a rigid cluster to its next rigid cluster (docs/method.md)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from itertools import combinations

import numpy as np

from packings.workers import kernels
from packings.workers.cluster import contacts_from_distances, pair_set, upper_pairs
from packings.workers.dimension import RIGID_PART, StressBasis, rigid_part, solution_dimension
from packings.workers.exact import SVD_ROUNDING, root_exists
from packings.workers.outcomes import (  # noqa: F401 - the outcomes of a path, named here too
    DIMENSION_CHANGED,
    FLOPPY,
    OVERLAP,
    PROJECTION_FAILED,
    RIGID,
    SHORTENS,
    TOO_LONG,
    UNDECIDED_END,
    UNPROVED,
)
from packings.workers.params import Params
from packings.workers.rigidity import (
    FIRST_ORDER,
    UNDECIDED,
    UNRESOLVED_METHOD,
    Rigidity,
    rigidity_from_null_spaces,
    rigidity_without_stress,
)
from packings.workers.rigidity import (
    FLOPPY as FLOPPY_KIND,
)

try:  # numba is a dependency; without it (or with a broken install) the reference still runs
    from packings.workers import _compiled
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
    adjacent = np.zeros((n, n), dtype=bool)
    adjacent[edges[:, 0], edges[:, 1]] = True
    adjacent[edges[:, 1], edges[:, 0]] = True
    upper = upper_pairs(n)
    return upper[~adjacent[upper[:, 0], upper[:, 1]]]


def follow_path(
    x: np.ndarray,
    keep: np.ndarray,
    broken: np.ndarray,
    tangent: np.ndarray,
    free: np.ndarray,
    params: Params,
    held_rows: np.ndarray | None = None,
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
    ``params.stop_on_dimension_change`` is set (the paper's rule); otherwise it
    goes on, carrying the tangent by least squares as at any singular point.
    Going on cannot produce a false cluster, since every endpoint is kept only
    if it passes the rigidity test; it reaches the rigid clusters that lie at the
    end of a singular path which a finite first step leaves (a thin set of
    dimension 2 surrounds such a path).

    ``held_rows``: rows of ``keep`` that a rigid part holds at their length near x
    (:func:`packings.workers.dimension.held_rows`).  The steps then project onto the
    other contacts, whose Jacobian has full row rank, rather than onto a set whose
    self-stresses persist along the whole path (each step's tangent an SVD, Newton's
    step the reduced one): the same curve.  The held rows stay contacts for all else
    (they are not watched as pairs that approach, and the endpoint is projected onto
    every contact kept).
    """
    steps_on = keep if held_rows is None else np.delete(np.asarray(keep).reshape(-1, 2), held_rows, axis=0)
    if kernels.compiled():
        return _follow_compiled(x, keep, broken, tangent, free, params, steps_on)
    return _follow_numpy(x, keep, broken, tangent, free, params, steps_on)


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


def _follow_numpy(x, keep, broken, tangent, free, params: Params, steps_on) -> PathEnd:
    """The reference loop of :func:`follow_path`: one Python iteration per step, an SVD at every step.
    ``steps_on``: the contacts the steps project onto."""
    n = x.size // 3
    kw = params.newton()
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
        pr = kernels.project(x + h * t, steps_on, free, **kw)
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
            return replace(_endpoint(x, xn, keep, pairs, hit, free, params, steps + 1), first_step_dim=first_dim)
        tn, dim = _svd_tangent(xn, steps_on, free, t, params, first_dim is None)
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
_COMPILED_OUTCOMES = (
    {
        _compiled.ST_PROJECTION_FAILED: PROJECTION_FAILED,
        _compiled.ST_SHORTENS: SHORTENS,
        _compiled.ST_DIMENSION_CHANGED: DIMENSION_CHANGED,
        _compiled.ST_TOO_LONG: TOO_LONG,
    }
    if _compiled is not None
    else {}
)


def _follow_compiled(x, keep, broken, tangent, free, params: Params, steps_on) -> PathEnd:
    """:func:`follow_path` with the stepping loop compiled (packings.workers._compiled.follow_steps).

    The compiled loop runs the same steps as :func:`_follow_numpy` and returns
    here only to end the path or when, on the first step, its rank guard cannot
    certify that R(xn) has full row rank (so that the null space is the
    complement of the row space, and the dimension is the reference's "regular"
    |V|).  That step takes its dimension and tangent from :func:`_svd_tangent`
    exactly as the reference does, and the compiled loop then resumes.  Later
    steps where the guard fails (a self-stress persists along the path) take
    the SVD's tangent inside the loop (``_compiled._svd_tangent``).  The steps
    project onto ``steps_on``.
    """
    n = x.size // 3
    x = kernels.as_kernel_array(x, np.float64, (-1,))
    keep = kernels.as_kernel_array(keep, np.int64, (-1, 2))
    steps_on = kernels.as_kernel_array(steps_on, np.int64, (-1, 2))
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
            x, t, d_prev, h, h_max, steps, first_dim is None, steps_on, free, mask, pairs, broken_idx,
            params.ds, h_min, params.tol, params.dx_max, params.newton_max_iter, params.tol_a0,
            params.max_path_steps, guard, params.stop_on_dimension_change, params.tol_n,
        )  # fmt: skip
        if dim >= 0:
            first_dim = int(dim)
        if status == _compiled.ST_HIT:
            return replace(_endpoint(x, xn, keep, pairs, hit, free, params, steps + 1), first_step_dim=first_dim)
        if status != _compiled.ST_NEED_SVD:
            return PathEnd(_COMPILED_OUTCOMES[status], steps, first_step_dim=first_dim)
        tn, dim = _svd_tangent(xn, steps_on, free, t, params, first_dim is None)
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


def max_move(a: np.ndarray, b: np.ndarray) -> float:
    """The largest displacement of a sphere between two flat coordinate vectors of one frame."""
    d = (np.asarray(a) - np.asarray(b)).reshape(-1, 3)
    return float(np.sqrt(np.einsum("ij,ij->i", d, d)).max(initial=0.0))


def approach_contact(
    x0: np.ndarray,
    x1: np.ndarray,
    keep: np.ndarray,
    pairs: np.ndarray,
    hit: np.ndarray,
    free: np.ndarray,
    params: Params,
    max_iter: int = 100,
) -> np.ndarray | None:
    """The point of the path through x0 and x1 (consecutive points on {f_keep = 0}) where the first
    approaching pair touches; ``pairs`` are the non-contact pairs, ``hit`` marks those that stopped
    the path at x1.

    The path stops once an approaching pair is within 1 + tol_a0 of touching.  Projecting that
    point onto the enlarged constraints at once is a Newton solve started up to tol_a0 from the
    contact, and along a slow approach far further along the path: Newton then leaves the basin
    of the contact and converges to another solution of the enlarged equations, far from the
    path (docs/method.md).  So the path is first walked to the contact, by a
    secant iteration on the smallest gap g of the approaching pairs against the distance along
    the path: each new point is predicted from the last two (along their chord, or between the
    two ends of a bracket once a point overlaps, Illinois) and projected onto the path's
    constraints; a step is at most ``ds0``, the path's own largest step.  A pair that comes within
    tol_a0 while approaching joins the pairs watched.  Converged when |g| <= sqrt(tol), finer than
    projected distances are resolved.  None when the gap stops decreasing before a bracket is
    found (the pairs pass by without touching), a projection fails, or it does not converge.
    """
    kw = params.newton()
    watched = hit.copy()
    d0 = kernels.pair_distances_flat(x0, pairs)
    d1 = kernels.pair_distances_flat(x1, pairs)
    y0, s0, g0 = x0, 0.0, float(d0[watched].min()) - 1.0
    y1, s1, g1 = x1, float(np.linalg.norm(x1 - x0)), float(d1[watched].min()) - 1.0
    g_tol = float(np.sqrt(params.tol))
    lo = (s0, g0, y0) if g0 > 0 else None  # bracket ends (s, g, y) with g > 0 and with g < 0
    hi = None
    side = 0  # Illinois: the end kept last time (1: lo, -1: hi)
    for _ in range(max_iter):
        if abs(g1) <= g_tol:
            return y1
        if g1 > 0:
            lo = (s1, g1, y1)
        else:
            hi = (s1, g1, y1)
        if lo is not None and hi is not None:
            (sa, ga, ya), (sb, gb, yb) = lo, hi
            ga, gb = (ga / 2, gb) if side == 1 else (ga, gb / 2) if side == -1 else (ga, gb)
            theta = ga / (ga - gb)
            s2, pred = sa + theta * (sb - sa), ya + theta * (yb - ya)
        else:
            if g1 >= g0 or s1 == s0:  # not approaching: the pairs pass by
                return None
            step = min(-g1 * (s1 - s0) / (g1 - g0), params.ds0)
            chord = y1 - y0
            s2, pred = s1 + step, y1 + step * chord / np.linalg.norm(chord)
        pr = kernels.project(pred, keep, free, **kw)
        if not pr.ok:
            return None
        d2 = kernels.pair_distances_flat(pr.x, pairs)
        watched |= (d2 < 1.0 + params.tol_a0) & (d2 < d1)
        g2 = float(d2[watched].min()) - 1.0
        if lo is not None and hi is not None:
            side = 1 if g2 < 0 else -1
        y0, s0, g0, y1, s1, g1, d1 = y1, s1, g1, pr.x, s2, g2, d2
    return None


def close_pairs(
    x: np.ndarray, edges: np.ndarray, extra: np.ndarray, free: np.ndarray, params: Params
) -> tuple[np.ndarray, tuple[tuple[int, int], ...]] | None:
    """Project x onto the contacts ``edges`` and the pairs ``extra``; (x', contacts of x') or None.

    The paper's procedure at a path's end: project onto the enlarged constraint set, deleting
    subsets of ``extra`` only when the projection fails (never all of them); adjacency is then
    decided with tol_a, and a pair within tol_a of touching that was not a constraint is added
    and the point projected again, since a contact must hold to Newton's tolerance like every
    other.  Every projection is polished and counts only if it moves no sphere by more than
    tol_a0 from x: the point sought is where these pairs touch, and tol_a0 is the distance at
    which the method takes a pair for a contact to be.  A projection that goes further has
    converged to another solution of the equations, not the one at x.  A point where two
    spheres overlap is returned as it is, for the caller to reject.
    """
    kw = params.newton()
    pr = None
    for r in range(max(1, len(extra))):
        for drop in combinations(range(len(extra)), r):
            sel = np.array([k for k in range(len(extra)) if k not in drop], dtype=np.int64)
            cons = np.vstack([edges, extra[sel]])
            pr = kernels.project(x, cons, free, polish=True, **kw)
            if pr.ok and max_move(pr.x, x) <= params.tol_a0:
                break
        else:
            continue
        break
    else:
        return None
    constrained = set(map(tuple, cons.tolist()))
    for _ in range(3):
        contacts = _contacts(pr.x, params.tol_a)
        if overlaps(pr.x, params):  # an overlapping pair is no contact to project onto: the caller rejects it
            return pr.x, contacts
        if set(contacts) <= constrained:
            y = _refined(pr, cons, free, x, params)
            return None if y is None else (y, contacts)
        # Without this, each near miss (a pair passing within tol_a) was stored as a rigid cluster of its own.
        cons = np.array(contacts, dtype=np.int64)
        pr = kernels.project(pr.x, cons, free, polish=True, **kw)
        if not pr.ok or max_move(pr.x, x) > params.tol_a0:
            return None
        constrained = set(contacts)
    return None


#: sum f^2 that a polished regular point reaches (round-off): above it, the point is singular
_ROUND_OFF = 1e-28


def _refined(
    pr: kernels.Projection, edges: np.ndarray, free: np.ndarray, x0: np.ndarray, params: Params
) -> np.ndarray | None:
    """A polished projection's point, refined along its flexes where it is singular
    (:func:`packings.workers.kernels.refine_singular`) so that two copies of one singular cluster agree far
    below tol_d; None if the refined point lies further than tol_a0 from x0 in some sphere.

    The refined point is the solution the polished one only approximates (along the flexes to about
    sqrt(|f| / margin)), so the projection counts only if it is within tol_a0 (:func:`close_pairs`).  The
    polished point is never kept in its place: it would be stored as a second copy of the cluster, more
    than tol_d from the first (docs/method.md)."""
    if pr.residual <= _ROUND_OFF:
        return pr.x
    y = kernels.refine_singular(pr.x, edges, free)
    return y if max_move(y, x0) <= params.tol_a0 else None


def near_pairs(x: np.ndarray, contacts, tol: float, candidates: np.ndarray | None = None) -> np.ndarray:
    """The pairs that are not ``contacts`` and are closer than 1 + tol, as a (k x 2) array; among
    ``candidates`` (pairs, some of which may be contacts) if given, else among all pairs."""
    n = x.size // 3
    if candidates is None:
        candidates = upper_pairs(n)
    close = candidates[kernels.pair_distances_flat(x, candidates) < 1.0 + tol]
    if not close.size:
        return close
    touching = pair_set(contacts)
    return close[[tuple(p) not in touching for p in close.tolist()]]


def resolve_near_pairs(
    x: np.ndarray, contacts, free: np.ndarray, params: Params, candidates: np.ndarray | None = None
) -> tuple[np.ndarray, tuple[tuple[int, int], ...], Rigidity] | None:
    """The rigid cluster that x (flat, pinned frame) becomes with its pairs within tol_a0 of
    touching as contacts, or None.

    x satisfies ``contacts``; its other pairs closer than 1 + tol_a0 are added (subsets deleted
    only when the projection fails, :func:`close_pairs`, which also keeps every sphere within
    tol_a0 of x).  If that projects, overlaps nothing and is rigid, it is the cluster x stands
    for: x is then a second solution of the same contact equations within tol_a0 of a cluster
    with more contacts, closer than the method resolves (docs/method.md).
    ``candidates``: the pairs that may be near (default all; a path passes its non-contacts).
    """
    near = near_pairs(x, contacts, params.tol_a0, candidates)
    if not near.size:
        return None
    alt = close_pairs(x, np.array(contacts, dtype=np.int64), near, free, params)
    if alt is None or overlaps(alt[0], params):
        return None
    rig = endpoint_rigidity(alt[0], alt[1], free, params)
    return (alt[0], alt[1], rig) if rig.rigid else None


def _endpoint(x_prev, x_hit, keep, pairs, hit, free, params: Params, steps: int) -> PathEnd:
    """The endpoint of a path that stopped at ``x_hit`` for the pairs ``pairs[hit]``, and its verdict.

    The paper's step first: add the pairs that stopped the path and project, deleting subsets of
    them only when that fails (:func:`close_pairs`, which counts a projection only if it moves
    no sphere further than tol_a0).  If none counts, or one overlaps, walk the path to where the
    first of them touches (:func:`approach_contact`) and do the same there with every pair
    touching.  Then the endpoint rule for pairs within tol_a0 of touching: if adding them gives
    a rigid cluster within tol_a0 (:func:`resolve_near_pairs`), that cluster is the endpoint;
    the point without them is a second solution of the same contact equations closer to it
    than the method resolves (docs/method.md).  With the compiled kernels the
    first projection and what is then looked at are one call (:func:`_close_at_hit`).
    """
    first = _close_at_hit(x_hit, keep, pairs, hit, free, params)
    if first is None:
        closed = close_pairs(x_hit, keep, pairs[hit], free, params)
        rejected, looked = closed is None or overlaps(closed[0], params), False
    else:
        rejected, closed = first
        looked = True  # no overlap, and no pair within tol_a0 that is not a contact
    if rejected:
        y = approach_contact(x_prev, x_hit, keep, pairs, hit, free, params)
        if y is None:
            return PathEnd(PROJECTION_FAILED, steps, new_contacts=_as_tuples(pairs[hit]))
        touching = pairs[kernels.pair_distances_flat(y, pairs) < 1.0 + params.tol_a]
        closed = close_pairs(y, keep, touching, free, params)
        if closed is None:
            return PathEnd(PROJECTION_FAILED, steps, new_contacts=_as_tuples(pairs[hit]))
        looked = False
    xe, contacts = closed
    coords = xe.reshape(-1, 3)
    if not looked:
        resolved = resolve_near_pairs(xe, contacts, free, params, pairs)
        if resolved is not None:
            xr, cr, rig = resolved
            return PathEnd(RIGID, steps, xr.reshape(-1, 3), cr, rig, _formed(cr, keep))
        if overlaps(xe, params):
            return PathEnd(OVERLAP, steps, coords, contacts, new_contacts=_formed(contacts, keep))
    rig = endpoint_rigidity(xe, contacts, free, params)
    outcome = (
        RIGID
        if rig.rigid
        else (UNPROVED if rig.method == UNPROVED_METHOD else UNDECIDED_END if rig.kind == UNDECIDED else FLOPPY)
    )
    return PathEnd(outcome, steps, coords, contacts, rig, _formed(contacts, keep))


def _close_at_hit(x_hit, keep, pairs, hit, free, params: Params):
    """:func:`_endpoint`'s first projection where the compiled kernel settles it
    (``packings.workers._compiled.close_at_hit``): (True, None) when :func:`close_pairs` would return
    nothing or an overlapping point; (False, (x, contacts)) when it would return x and its contacts
    and neither :func:`resolve_near_pairs` nor :func:`overlaps` has anything to say there.  None
    elsewhere, and with the numpy backend: then :func:`_endpoint` decides it all in Python.
    """
    if not kernels.compiled():
        return None
    n = x_hit.size // 3
    upper = _kernel_pairs(n)
    status, x, d = _compiled.close_at_hit(
        x_hit, kernels.as_kernel_array(keep, np.int64, (-1, 2)), pairs, hit, free, kernels.free_mask(x_hit.size, free),
        upper, params.tol, params.dx_max, params.newton_max_iter, kernels.guard_threshold(params.tol_n), params.tol_a,
        params.tol_a0, _ROUND_OFF,
    )  # fmt: skip
    if status == _compiled.CH_REJECTED:
        return True, None
    if status == _compiled.CH_CLOSED:
        return False, (x, contacts_from_distances(upper, d, params.tol_a))
    return None


@functools.lru_cache(maxsize=None)
def _kernel_pairs(n: int) -> np.ndarray:
    """upper_pairs(n) as the compiled kernels take it (writeable, as a read-only array would compile another
    variant of each kernel; shared, so never written)."""
    return upper_pairs(n).copy()


def _as_tuples(pairs: np.ndarray) -> tuple[tuple[int, int], ...]:
    return tuple(map(tuple, pairs.tolist()))


def _formed(contacts, keep) -> tuple[tuple[int, int], ...]:
    """The contacts of an endpoint that the path did not keep: the ones it formed."""
    kept = pair_set(keep)
    return tuple(c for c in contacts if c not in kept)


def overlaps(x: np.ndarray, params: Params) -> bool:
    """Whether two spheres of ``x`` (flat) overlap: a pair closer than 1 - tol_a."""
    return bool(kernels.pair_distances_flat(x, upper_pairs(x.size // 3)).min(initial=np.inf) < 1.0 - params.tol_a)


def _contacts(x: np.ndarray, tol_a: float) -> tuple[tuple[int, int], ...]:
    """The pairs of ``x`` (flat) closer than 1 + tol_a, sorted: contacts_from_coords by the pair-distance kernel."""
    pairs = upper_pairs(x.size // 3)
    return contacts_from_distances(pairs, kernels.pair_distances_flat(x, pairs), tol_a)


UNPROVED_METHOD = "unproved"  #: Rigidity.method of a first-order verdict Kantorovich's theorem did not bear out


def _held_by_a_rigid_part(
    rig: Rigidity, x: np.ndarray, edges: np.ndarray, ns: kernels.NullSpaces, tol_n: float
) -> bool:
    """Whether the pre-stress test found no definite combination (not merely one whose margin the
    coordinates leave in doubt, method ``unresolved``) and every self-stress lies in a rigid part.  An
    undecided verdict of that test has flexes and stresses both."""
    return (
        rig.kind == UNDECIDED
        and rig.method != UNRESOLVED_METHOD
        and rigid_part(x, edges, StressBasis.of(ns, tol_n, pinv=False), tol_n) is not None
    )


def endpoint_rigidity(x: np.ndarray, contacts, free: np.ndarray, params: Params) -> Rigidity:
    """The rigidity test of an endpoint (x flat, in the pinned frame of ``free``): without the SVD
    where the compiled kernels certify full row rank, and with the isolation probe for a
    pre-stress verdict (packings.workers.rigidity.rigidity_from_null_spaces).

    A first-order verdict stands only where Kantorovich's theorem proves a root of the contact
    equations near x (:func:`packings.workers.exact.kantorovich`); otherwise x only satisfied Newton's
    tolerance, near no cluster, and the verdict is undecided, method ``unproved``
    (docs/method.md).  An undecided pre-stress verdict is floppy, method ``rigid-part``,
    where every self-stress lies in an infinitesimally rigid part (:func:`packings.workers.dimension.rigid_part`):
    the contacts near x then form a manifold of dimension |V| > 0 (the pre-stress forms vanish on its
    flexes, so the test could only leave it undecided)."""
    edges = np.array(contacts, dtype=np.int64)
    flexes = kernels.regular_flexes(x, edges, free, params.tol_n)
    if flexes is not None:  # certified full row rank: what the SVD would find, without it
        rig = rigidity_without_stress(flexes)
        sigma_min = math.sqrt(kernels.guard_threshold(params.tol_n))  # what the certificate proves
    else:
        ns = kernels.null_spaces(x, edges, free, params.tol_n)
        rig = rigidity_from_null_spaces(ns, edges, params, x, free)
        if _held_by_a_rigid_part(rig, x, edges, ns, params.tol_n):
            return Rigidity(False, FLOPPY_KIND, rig.flexes, rig.stresses, RIGID_PART, rig.margin)
        sigma_min = float(ns.sigma[-1] - SVD_ROUNDING * ns.sigma[0]) if ns.sigma.size else None
    if rig.kind == FIRST_ORDER and not root_exists(x, edges, free, params.tol_n, sigma_min):
        return Rigidity(False, UNDECIDED, 0, rig.stresses, UNPROVED_METHOD)
    return rig
