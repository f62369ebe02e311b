"""Dimension of the solution set: the regular (rank) branch and the numerical estimate."""

import json
from itertools import combinations
from pathlib import Path

import numpy as np

from workers import kernels
from workers.cluster import Cluster
from workers.dimension import solution_dimension
from workers.params import Params
from workers.rigidity import contact_triangle
from workers.seeds import seed_cluster

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
