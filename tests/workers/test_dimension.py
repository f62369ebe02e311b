"""Dimension of the solution set: the regular (rank) branch and the numerical estimate."""

import json
from itertools import combinations
from pathlib import Path

import numpy as np

from packings.workers import dimension, kernels
from packings.workers.cluster import Cluster
from packings.workers.dimension import solution_dimension
from packings.workers.params import Params
from packings.workers.rigidity import contact_triangle
from packings.workers.seeds import seed_cluster

P = Params()
FIXTURES = json.loads((Path(__file__).parents[1] / "data" / "clusters_n10.json").read_text())


def dim_after_breaking(c: Cluster, idx):
    e = c.edges()
    keep = np.delete(e, list(idx), axis=0)
    tri = contact_triangle(keep)
    x = kernels.to_frame(c.coords, tri).ravel()
    return solution_dimension(x, keep, kernels.free_coordinates(c.n, tri), P), x, keep


def test_regular_branch_counts_flexes():
    c = seed_cluster(9)
    for k in (1, 2, 3):
        d, x, keep = dim_after_breaking(c, range(k, 2 * k))
        assert d.method == "regular"
        assert d.dim == k
        R = kernels.rigidity_matrix(x, keep)
        assert np.allclose(R @ d.tangents, 0, atol=1e-10)


def test_numerical_branch_on_a_singular_cluster():
    """Breaking two contacts of a singular 24-contact cluster: the rank test cannot decide;
    the numerical estimate finds one-dimensional and two-dimensional cases, and its tangent is a flex."""
    c = Cluster.from_dict(FIXTURES["n10_m24_prestress"])
    seen = {}
    for idx in combinations(range(c.m), 2):
        d, x, keep = dim_after_breaking(c, idx)
        if d.method != "numerical":
            continue
        seen.setdefault(d.dim, (d, x, keep))
        if 1 in seen and 2 in seen:
            break
    assert 1 in seen and 2 in seen
    d, x, keep = seen[1]
    t = d.tangents[:, 0]
    assert abs(np.linalg.norm(t) - 1) < 1e-12
    # a secant of the path over one probe step: almost entirely a linear flex
    tri = contact_triangle(keep)
    V = kernels.null_spaces(x, keep, kernels.free_coordinates(c.n, tri), P.tol_n).V
    assert np.linalg.norm(V.T @ t) > 0.99


def _numerical_cases(c: Cluster, size: int, params: Params):
    """(idx, x, keep, free) for every ``size``-subset of contacts of ``c`` whose dimension needs the numerical estimate."""
    e = c.edges()
    for idx in combinations(range(c.m), size):
        keep = np.delete(e, list(idx), axis=0)
        tri = contact_triangle(keep)
        x = kernels.to_frame(c.coords, tri).ravel()
        free = kernels.free_coordinates(c.n, tri)
        ns = kernels.null_spaces(x, keep, free, params.tol_n)
        if ns.W.shape[1] and ns.V.shape[1]:
            yield idx, x, keep, free


def test_giving_up_stalled_probe_projections_changes_no_dimension(monkeypatch):
    """The probes' orthogonal projections stop once their residual stalls (probe_stall): on every
    two-contact break of the singular n = 10 cluster that needs the numerical estimate, the
    dimension and the tangent basis are those of probes that run all newton_max_iter iterations.
    (Every orthogonal projection is run here, even those the exact bound excludes.)"""
    monkeypatch.setattr(dimension, "orthogonal_may_be_accepted", lambda *a: True)
    c = Cluster.from_dict(FIXTURES["n10_m24_prestress"])
    full = P.with_(probe_stall=0)
    assert P.probe_stall > 0
    dims = set()
    for idx, x, keep, free in _numerical_cases(c, 2, P):
        a = solution_dimension(x, keep, free, P)
        b = solution_dimension(x, keep, free, full)
        assert (a.dim, a.method) == (b.dim, b.method), idx
        assert np.allclose(a.tangents, b.tangents, atol=1e-9), idx
        dims.add(a.dim)
    assert {1, 2} <= dims


def test_a_limit_stops_probing_above_it_and_keeps_the_first_directions():
    c = Cluster.from_dict(FIXTURES["n10_m24_prestress"])
    seen = set()
    for idx, x, keep, free in _numerical_cases(c, 2, P):
        full = solution_dimension(x, keep, free, P)
        lim = solution_dimension(x, keep, free, P, limit=1)
        assert lim.dim == min(full.dim, 2), idx
        assert lim.at_least == (full.dim > 1)
        assert not full.at_least
        k = min(full.dim, 2)
        assert np.array_equal(lim.tangents, full.tangents[:, :k]), idx
        seen.add(full.dim)
    assert {1, 2} <= seen


def test_orthogonal_projections_are_skipped_only_where_they_could_not_be_accepted():
    """orthogonal_may_be_accepted is a proof, not a heuristic: wherever it says no, the orthogonal
    projection, run to the end, converges to nothing the probe accepts."""
    c = Cluster.from_dict(FIXTURES["n10_m24_prestress"])
    kw = dict(tol=P.tol, dx_max=P.dx_max, max_iter=P.newton_max_iter, tol_n=P.tol_n)
    skipped = converged = 0
    for idx, x, keep, free in _numerical_cases(c, 2, P):
        V = kernels.null_spaces(x, keep, free, P.tol_n).V
        for j in range(V.shape[1]):
            for step in (P.ds0, -P.ds0):
                v = V[:, j]
                x0 = x + step * v
                if dimension.orthogonal_may_be_accepted(x0, keep, step, float(np.linalg.norm(v[free])), P):
                    continue
                skipped += 1
                pr = kernels.project(x0, keep, free, extra=(v[free][None, :], np.array([v[free] @ x0[free]])), **kw)
                if pr.ok:
                    converged += 1
                    assert np.linalg.norm(pr.x - x) > P.x_tol_max, idx
    assert skipped > 50 and converged > 20
    # a looser x_tol_max leaves room for an orthogonal correction: then it is always run
    loose = P.with_(x_tol_max=2 * P.ds0)
    idx, x, keep, free = next(_numerical_cases(c, 2, P))
    v = kernels.null_spaces(x, keep, free, P.tol_n).V[:, 0]
    assert dimension.orthogonal_may_be_accepted(x + P.ds0 * v, keep, P.ds0, 1.0, loose)
    # and a stricter one than the probe step never accepts it
    assert not dimension.orthogonal_may_be_accepted(x + P.ds0 * v, keep, P.ds0, 1.0, P.with_(x_tol_max=0.9 * P.ds0))
