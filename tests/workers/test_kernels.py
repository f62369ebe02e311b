"""Kernels: residuals, the rigidity matrix, Newton projection, null spaces."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packings.workers import kernels
from packings.workers.params import Params
from packings.workers.rigidity import contact_triangle
from packings.workers.seeds import seed_cluster

P = Params()


def _flat(c):
    return np.ascontiguousarray(c.coords).ravel().copy()


@settings(max_examples=25, deadline=None, derandomize=True)
@given(st.integers(5, 10), st.integers(0, 2**31 - 1))
def test_rigidity_matrix_is_half_the_jacobian(n, seed):
    rng = np.random.default_rng(seed)
    c = seed_cluster(n)
    e = c.edges()
    x = _flat(c) + 0.1 * rng.standard_normal(3 * n)
    y = rng.standard_normal(3 * n)
    h = 1e-6
    numeric = (kernels.residual(x + h * y, e) - kernels.residual(x - h * y, e)) / (2 * h)
    R = kernels.rigidity_matrix(x, e)
    assert np.allclose(2 * R @ y, numeric, atol=1e-6)
    # (R(p) y)_k = (p_i - p_j).(y_i - y_j)
    p, q = x.reshape(-1, 3), y.reshape(-1, 3)
    direct = np.einsum("kx,kx->k", p[e[:, 0]] - p[e[:, 1]], q[e[:, 0]] - q[e[:, 1]])
    assert np.allclose(R @ y, direct)


def test_to_frame_pins_the_triangle_and_keeps_distances():
    c = seed_cluster(8)
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    moved = c.coords @ q.T + rng.standard_normal(3)
    f = kernels.to_frame(moved, (0, 1, 2))
    assert np.allclose(f[0], 0) and np.allclose(f[1, 1:], 0) and abs(f[2, 2]) < 1e-15 and f[2, 1] > 0
    d0 = np.linalg.norm(moved[:, None] - moved[None], axis=-1)
    d1 = np.linalg.norm(f[:, None] - f[None], axis=-1)
    assert np.allclose(d0, d1, atol=1e-12)
    assert np.linalg.det(np.linalg.lstsq(moved - moved.mean(0), f - f.mean(0), rcond=None)[0]) > 0


def test_projection_returns_to_the_constraint_set():
    c = seed_cluster(9)
    tri = (0, 1, 2)
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(9, tri)
    rng = np.random.default_rng(0)
    x0 = x.copy()
    x0[free] += 0.01 * rng.standard_normal(free.size)
    pr = kernels.project(x0, c.edges(), free, tol=P.tol, dx_max=P.dx_max, max_iter=P.newton_max_iter)
    assert pr.ok
    assert np.sum(kernels.residual(pr.x, c.edges()) ** 2) < P.tol
    pinned = kernels.pinned_coordinates(tri)
    assert np.array_equal(pr.x[pinned], x0[pinned])


def test_projection_reports_failure_for_impossible_contacts():
    # five spheres all touching each other cannot exist in 3D
    c = seed_cluster(5)
    edges = np.array([(i, j) for i in range(5) for j in range(i + 1, 5)])
    x = kernels.to_frame(c.coords, (0, 1, 2)).ravel()
    pr = kernels.project(x, edges, kernels.free_coordinates(5, (0, 1, 2)), tol=P.tol, dx_max=P.dx_max, max_iter=50)
    assert not pr.ok
    assert pr.residual > P.tol


@pytest.mark.parametrize("name", kernels.BACKENDS)
def test_a_stalled_projection_gives_up_early(name):
    """stall=k: Newton stops, failed, once sum f^2 has not improved for k iterations; a
    projection that converges is unaffected."""
    c = seed_cluster(5)
    edges = np.array([(i, j) for i in range(5) for j in range(i + 1, 5)])  # impossible in 3D
    x = kernels.to_frame(c.coords, (0, 1, 2)).ravel()
    free = kernels.free_coordinates(5, (0, 1, 2))
    kw = dict(tol=P.tol, dx_max=P.dx_max, max_iter=200)
    with kernels.backend(name):
        full = kernels.project(x, edges, free, **kw)
        early = kernels.project(x, edges, free, stall=5, **kw)
        assert not full.ok and full.iterations == 200
        assert not early.ok and early.iterations < 200
        assert early.residual > P.tol
        good = seed_cluster(9)
        e9 = good.edges()[1:]
        tri = contact_triangle(e9)
        x9 = kernels.to_frame(good.coords, tri).ravel()
        f9 = kernels.free_coordinates(9, tri)
        x9p = x9.copy()
        x9p[f9] += 1e-3 * np.random.default_rng(1).standard_normal(f9.size)
        a = kernels.project(x9p, e9, f9, **kw)
        b = kernels.project(x9p, e9, f9, stall=2, **kw)
        assert a.ok and b.ok and np.array_equal(a.x, b.x) and a.iterations == b.iterations


def test_polish_reaches_round_off():
    c = seed_cluster(10)
    tri = (0, 1, 2)
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(10, tri)
    x0 = x + 1e-3 * np.random.default_rng(1).standard_normal(x.size) * np.isin(np.arange(x.size), free)
    kw = dict(tol=P.tol, dx_max=P.dx_max, max_iter=P.newton_max_iter)
    rough = kernels.project(x0, c.edges(), free, **kw)
    fine = kernels.project(x0, c.edges(), free, polish=True, **kw)
    assert rough.ok and fine.ok
    assert fine.residual <= rough.residual
    assert fine.residual < 1e-28


def test_null_spaces_of_isostatic_cluster_minus_one_contact():
    c = seed_cluster(8)
    e = c.edges()
    tri = (0, 1, 2)  # the seed's first tetrahedron
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(8, tri)
    ns = kernels.null_spaces(x, e, free, P.tol_n)
    assert ns.V.shape[1] == 0 and ns.W.shape[1] == 0
    ns1 = kernels.null_spaces(x, np.delete(e, 5, 0), free, P.tol_n)
    assert ns1.V.shape[1] == 1 and ns1.W.shape[1] == 0
    R = kernels.rigidity_matrix(x, np.delete(e, 5, 0))
    assert np.allclose(R @ ns1.V[:, 0], 0, atol=1e-12)
    assert np.allclose(ns1.V[kernels.pinned_coordinates(tri), 0], 0)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(st.integers(4, 12), st.integers(0, 2**31 - 1), st.sampled_from([1e-3, 1e-5]))
def test_an_endpoints_contacts_are_contacts_from_coords(n, seed, tol_a):
    """The endpoint's contacts (distances by the pair-distance kernel, each backend) are what
    contacts_from_coords finds, on clusters with pairs within 1e-9 of each side of 1 + tol_a."""
    from packings.workers.cluster import contacts_from_coords
    from packings.workers.paths import _contacts

    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, 1.5, size=(n, 3))
    for _ in range(3):  # move sphere j onto the threshold of sphere i, just inside or just outside
        i, j = rng.choice(n, size=2, replace=False)
        u = rng.normal(size=3)
        x[j] = x[i] + (1.0 + tol_a + rng.choice([-1e-9, 1e-9])) * u / np.linalg.norm(u)
    want = contacts_from_coords(x, tol_a)
    assert want == tuple(sorted(want))
    for name in kernels.BACKENDS:
        with kernels.backend(name):
            assert _contacts(x.ravel(), tol_a) == want


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.integers(3, 14), st.integers(0, 2**31 - 1), st.booleans())
def test_aligned_max_error_is_zero_for_a_turned_copy_and_bounded_below_for_a_moved_one(n, seed, reflect):
    """The orthogonal Procrustes alignment undoes any rotation or reflection of a centred cluster (the
    error is round-off).  For any other y it is at least the largest change of a pair distance over
    2 sqrt(3): an orthogonal R keeps x's distances, so |r_i - r_j| >= | |x_i - x_j| - |y_i - y_j| | for
    the residuals r = x R - y, and each |r_i| is at most sqrt(3) times the error (a coordinate's)."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, 3))
    x -= x.mean(axis=0)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    if (np.linalg.det(q) < 0) != reflect:
        q[:, 0] *= -1
    scale = 1e-12 * (1.0 + np.abs(x).max())
    assert kernels.aligned_max_error(x, x @ q) <= scale
    assert kernels.aligned_max_error(x @ q, x) <= scale
    y = x @ q
    y[rng.integers(n)] += 0.3 * rng.standard_normal(3)
    y -= y.mean(axis=0)
    dx = np.linalg.norm(x[:, None] - x[None], axis=-1)
    dy = np.linalg.norm(y[:, None] - y[None], axis=-1)
    assert kernels.aligned_max_error(x, y) >= np.abs(dx - dy).max() / (2.0 * 3.0**0.5) - scale
