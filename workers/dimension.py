"""Dimension of the solution set near x after contacts are deleted (METHOD.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers import kernels
from workers.params import Params
from workers.rigidity import Rigidity, rigidity_from_null_spaces


@dataclass(frozen=True)
class Dimension:
    """D, an orthonormal basis of the tangent directions found (3n x D), and how D was decided.

    ``method`` is ``regular`` (R has full row rank: D = |V|), ``rigid`` (the
    rigidity test says the point is isolated) or ``numerical`` (tangent-space
    estimate).
    """

    dim: int
    tangents: np.ndarray
    method: str
    rigidity: Rigidity | None = None


def solution_dimension(
    x: np.ndarray,
    edges: np.ndarray,
    free: np.ndarray,
    params: Params,
    ns: kernels.NullSpaces | None = None,
) -> Dimension:
    """Dimension of {f = 0} near x, with the pinned coordinates fixed.

    If R has full row rank and no more rows than columns, D = |V|.  Otherwise the
    rigidity test decides D = 0, and failing that the numerical estimate:
    for each v_j in V and each sign, step x + s ds v_j, project back (first with
    the correction orthogonal to v_j, then without), accept the displacement
    v_t = x' - x if x_tol_min <= |v_t| <= x_tol_max, and keep its unit direction
    if its part orthogonal to the directions already found exceeds v_tol.  A
    pair of opposite probes along one v_j is combined into their difference,
    which cancels the curvature of the path to second order.
    """
    if ns is None:
        ns = kernels.null_spaces(x, edges, free, params.tol_n)
    V, W = ns.V, ns.W
    if W.shape[1] == 0:
        return Dimension(V.shape[1], V, "regular")
    rig = rigidity_from_null_spaces(ns, edges, params)
    if rig.rigid:
        return Dimension(0, V[:, :0], "rigid", rig)
    h = params.ds
    basis: list[np.ndarray] = []
    for j in range(V.shape[1]):
        v = V[:, j]
        probes = []
        for s in (1.0, -1.0):
            vt = _probe(x, v, s * h, edges, free, params)
            if vt is not None:
                probes.append(vt)
        if len(probes) == 2 and probes[0] @ probes[1] < -0.9 * np.linalg.norm(probes[0]) * np.linalg.norm(probes[1]):
            probes = [probes[0] - probes[1]]
        for vt in probes:
            u = vt / np.linalg.norm(vt)
            for b in basis:
                u = u - (b @ u) * b
            r = np.linalg.norm(u)
            if r > params.v_tol:
                basis.append(u / r)
    t = np.stack(basis, axis=1) if basis else V[:, :0]
    return Dimension(len(basis), t, "numerical", rig)


def _probe(x, v, step, edges, free, params: Params) -> np.ndarray | None:
    """Displacement to the solution set from x + step v, or None if it is rejected."""
    x0 = x + step * v
    kw = dict(tol=params.tol, dx_max=params.dx_max, max_iter=params.newton_max_iter)
    pr = kernels.project(x0, edges, free, extra=(v[free][None, :], np.array([v[free] @ x0[free]])), **kw)
    if not pr.ok or np.linalg.norm(pr.x - x) > params.x_tol_max:
        pr = kernels.project(x0, edges, free, **kw)
    if not pr.ok:
        return None
    vt = pr.x - x
    size = np.linalg.norm(vt)
    if size > params.x_tol_max or size < params.x_tol_min:
        return None
    return vt
