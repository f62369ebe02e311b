"""The compiled (numba) kernels against the numpy reference (packings.workers.kernels backends).

(a) Following the same paths with both backends gives the same results.
(b) The compiled residual, rigidity matrix, Newton projection, tangent
    projection and rank certificate agree with numpy on random inputs, and are
    invariant under rotation and relabelling where that applies.
(c) The numpy reference can still be selected (function, context manager,
    environment variable).
"""

import json
import os
import subprocess
import sys
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packings.workers import _compiled, kernels
from packings.workers import paths as paths_module
from packings.workers.cluster import Cluster
from packings.workers.expand import expand, path_starts, warm_up
from packings.workers.identity import certificate, same_geometry
from packings.workers.params import Params
from packings.workers.paths import PROJECTION_FAILED, RIGID, UNDECIDED_END, follow_path
from packings.workers.rigidity import contact_triangle
from packings.workers.seeds import seed_cluster
from tests.helpers import congruent_copy, random_orthogonal

P = Params()
ROOT = Path(__file__).parents[2]
FIXTURES = json.loads((ROOT / "tests" / "data" / "clusters_n10.json").read_text())


@pytest.fixture(autouse=True)
def _restore_backend():
    previous = kernels.get_backend()
    yield
    kernels.set_backend(previous)


# --------------------------------------------------------------------------- (a) same paths, same results


def _clusters_reached(n: int, count: int) -> list[Cluster]:
    """The seed of n spheres and the first rigid clusters one expansion of it reaches."""
    seed = seed_cluster(n)
    with kernels.backend("numpy"):
        ends = [e.cluster for e in expand(seed, P).rigid_endpoints()]
    return [seed] + ends[: count - 1]


def _sample(starts, k: int, seed: int):
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(len(starts), size=min(k, len(starts)), replace=False))
    return [starts[i] for i in idx]


@pytest.fixture(scope="module")
def path_sample():
    """A fixed, seeded set of (label, PathStart): n = 8..11, and every path of the singular n = 10 fixtures."""
    out = []
    for n, k in ((8, 12), (9, 12), (11, 12)):
        starts = [p for c in _clusters_reached(n, 3) for p in path_starts(c, P)]
        out += [(f"n{n}", p) for p in _sample(starts, k, seed=n)]
    for name, raw in FIXTURES.items():
        starts = path_starts(Cluster.from_dict(raw), P)
        chosen = starts if "prestress" in name else _sample(starts, 12, seed=10)
        out += [(name, p) for p in chosen]
    return out


def _follow_all(sample, backend):
    with kernels.backend(backend):
        return [p.follow(P) for _, p in sample]


def test_both_backends_follow_paths_to_the_same_ends(path_sample):
    compiled = _follow_all(path_sample, "numba")
    reference = _follow_all(path_sample, "numpy")
    rigid = 0
    sensitive = []
    for (label, p), a, b in zip(path_sample, compiled, reference):
        where = (label, p.broken_contacts, p.direction)
        assert a.first_step_dim == b.first_step_dim, where
        if a.outcome != b.outcome and RIGID not in (a.outcome, b.outcome):
            sensitive.append((where, (a.outcome, b.outcome)))
            continue
        assert a.outcome == b.outcome, where
        if a.outcome == RIGID:
            rigid += 1
            assert a.steps == b.steps, where
            assert a.contacts == b.contacts and a.new_contacts == b.new_contacts, where
            ca, cb = Cluster(a.coords, a.contacts), Cluster(b.coords, b.contacts)
            assert certificate(ca) == certificate(cb), where
            assert same_geometry(ca, cb, P.tol_d), where
            assert (a.rigidity.kind, a.rigidity.flexes, a.rigidity.stresses) == (
                b.rigidity.kind,
                b.rigidity.flexes,
                b.rigidity.stresses,
            ), where
            if (
                a.rigidity.flexes == 0 and a.rigidity.stresses == 0
            ):  # regular, isostatic: Newton reaches round-off in both
                assert np.abs(a.coords - b.coords).max() < 1e-9, where
        elif a.steps != b.steps or a.contacts != b.contacts:
            sensitive.append((where, (a.outcome, b.outcome)))
    assert rigid > 60
    # Paths may differ only where the reference itself does under round-off, and never at a rigid
    # end: at points reached through singular sets (a continuum of nearby endpoints), which end
    # undecided, or fail the endpoint's projection where it would have to move further than tol_a0.
    assert all(set(outcomes) <= {UNDECIDED_END, PROJECTION_FAILED} for _, outcomes in sensitive), sensitive
    assert len(sensitive) <= 2


def test_the_compiled_endpoint_call_gives_the_endpoint_python_gives(path_sample, monkeypatch):
    """paths._close_at_hit (the first projection of a path's end and what is looked at there, in one
    compiled call) changes no endpoint: every path ends exactly, bit for bit, as with the Python code
    alone, and the sample holds endpoints the call settles both ways and some it hands back."""
    statuses = []
    real = _compiled.close_at_hit

    def recording(*args):
        out = real(*args)
        statuses.append(out[0])
        return out

    monkeypatch.setattr(_compiled, "close_at_hit", recording)
    with_call = _follow_all(path_sample, "numba")
    monkeypatch.setattr(paths_module, "_close_at_hit", lambda *args: None)
    python_only = _follow_all(path_sample, "numba")
    for (label, p), a, b in zip(path_sample, with_call, python_only):
        where = (label, p.broken_contacts, p.direction)
        assert (a.outcome, a.steps, a.first_step_dim, a.contacts, a.new_contacts) == (
            b.outcome,
            b.steps,
            b.first_step_dim,
            b.contacts,
            b.new_contacts,
        ), where
        assert (a.coords is None) == (b.coords is None) and (a.coords is None or np.array_equal(a.coords, b.coords)), (
            where
        )
        assert repr(a.rigidity) == repr(b.rigidity), where
    assert {_compiled.CH_CLOSED, _compiled.CH_REJECTED, _compiled.CH_PYTHON} <= set(statuses), sorted(set(statuses))
    assert statuses.count(_compiled.CH_CLOSED) > len(statuses) // 2


def test_the_compiled_loop_defers_to_the_svd_where_the_guard_fails(monkeypatch):
    """With a guard no matrix passes, every Newton step is least squares and every tangent the SVD's
    (the first step's from Python, with the dimension test; the others from the compiled SVD in the
    loop): the compiled loop then runs the reference's arithmetic, and must give its results."""
    monkeypatch.setattr(kernels, "GUARD_FACTOR", 1e30)
    starts = _sample([p for c in _clusters_reached(9, 2) for p in path_starts(c, P)], 10, seed=1)
    starts += _sample(path_starts(Cluster.from_dict(FIXTURES["n10_m24_prestress"]), P), 6, seed=2)
    calls = []
    real = paths_module._svd_tangent

    def counting(*args):
        calls.append(1)
        return real(*args)

    monkeypatch.setattr(paths_module, "_svd_tangent", counting)
    compiled = [p.follow(P) for p in starts]
    assert len(calls) <= len(starts) < sum(e.steps for e in compiled)  # Python only for first steps
    with kernels.backend("numpy"):
        reference = [p.follow(P) for p in starts]
    for a, b in zip(compiled, reference):
        assert (a.outcome, a.steps, a.first_step_dim, a.contacts) == (b.outcome, b.steps, b.first_step_dim, b.contacts)
        if a.outcome == RIGID:
            assert same_geometry(Cluster(a.coords, a.contacts), Cluster(b.coords, b.contacts), P.tol_d)


# --------------------------------------------------------------------------- (b) kernels on random inputs


@st.composite
def random_graphs(draw):
    n = draw(st.integers(2, 14))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)], dtype=np.int64)
    keep = rng.random(len(pairs)) < draw(st.floats(0.1, 1.0))
    return n, pairs[keep].reshape(-1, 2), rng


@settings(max_examples=60, deadline=None, derandomize=True)
@given(random_graphs())
def test_residual_rigidity_matrix_and_distances_match_numpy(graph):
    n, edges, rng = graph
    x = rng.standard_normal(3 * n)
    with kernels.backend("numba"):
        f, R, d = kernels.residual(x, edges), kernels.rigidity_matrix(x, edges), kernels.pair_distances_flat(x, edges)
    with kernels.backend("numpy"):
        f0, R0, d0 = (
            kernels.residual(x, edges),
            kernels.rigidity_matrix(x, edges),
            kernels.pair_distances_flat(x, edges),
        )
    assert f.shape == f0.shape and R.shape == R0.shape and d.shape == d0.shape
    assert np.allclose(f, f0, rtol=1e-13, atol=1e-13)
    assert np.array_equal(R, R0)
    assert np.allclose(d, d0, rtol=1e-14, atol=0)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(random_graphs())
def test_compiled_kernels_are_invariant_under_rotation_and_relabelling(graph):
    n, edges, rng = graph
    x = rng.standard_normal(3 * n)
    y = rng.standard_normal(3 * n)
    q = random_orthogonal(rng, False)
    shift = rng.standard_normal(3)
    xr = (x.reshape(-1, 3) @ q.T + shift).ravel()
    yr = (y.reshape(-1, 3) @ q.T).ravel()
    perm = rng.permutation(n)  # new label of sphere i is inv[i]; sphere k of the relabelled cluster is old perm[k]
    inv = np.argsort(perm)
    xp = x.reshape(-1, 3)[perm].ravel()
    yp = y.reshape(-1, 3)[perm].ravel()
    ep = np.sort(inv[edges], axis=1)
    with kernels.backend("numba"):
        f, R = kernels.residual(x, edges), kernels.rigidity_matrix(x, edges)
        # rigid motions: residuals unchanged, and R(Qx + c)(Qy) = R(x) y
        assert np.allclose(kernels.residual(xr, edges), f, atol=1e-12)
        assert np.allclose(kernels.rigidity_matrix(xr, edges) @ yr, R @ y, atol=1e-12)
        # relabelling: the same residuals and (R y)_k, contact by contact
        assert np.allclose(kernels.residual(xp, ep), f, atol=1e-15)
        assert np.allclose(kernels.rigidity_matrix(xp, ep) @ yp, R @ y, atol=1e-12)


def _perturbed_problem(n, drop, eps, seed):
    """A seed cluster in the frame of its first triangle, with ``drop`` contacts removed and the free coordinates perturbed."""
    rng = np.random.default_rng(seed)
    c = seed_cluster(n)
    edges = c.edges()
    tri = contact_triangle(edges)
    tri_edges = {(tri[0], tri[1]), (tri[0], tri[2]), (tri[1], tri[2])}
    removable = [k for k, e in enumerate(map(tuple, edges.tolist())) if e not in tri_edges]
    keep = np.delete(edges, rng.choice(removable, size=drop, replace=False), axis=0)
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(n, tri)
    x0 = x.copy()
    x0[free] += eps * rng.standard_normal(free.size)
    return x0, keep, free, tri, rng


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.integers(5, 12), st.integers(0, 3), st.floats(1e-5, 2e-2), st.booleans(), st.integers(0, 2**31 - 1))
def test_compiled_newton_projection_matches_numpy(n, drop, eps, polish, seed):
    x0, keep, free, _, _ = _perturbed_problem(n, drop, eps, seed)
    kw = dict(tol=P.tol, dx_max=P.dx_max, max_iter=P.newton_max_iter, polish=polish)
    with kernels.backend("numba"):
        a = kernels.project(x0, keep, free, **kw)
    with kernels.backend("numpy"):
        b = kernels.project(x0, keep, free, **kw)
    assert a.ok and b.ok
    assert np.sum(kernels.residual_numpy(a.x, keep) ** 2) < P.tol
    pinned = np.setdiff1d(np.arange(x0.size), free)
    assert np.array_equal(a.x[pinned], x0[pinned])
    assert np.abs(a.x - b.x).max() < 1e-9
    if drop == 0:
        assert abs(a.iterations - b.iterations) <= 2  # the polish stops on round-off, which may differ


@settings(max_examples=30, deadline=None, derandomize=True)
@given(
    st.integers(5, 11),
    st.integers(0, 2),
    st.floats(1e-4, 5e-2),
    st.sampled_from([0, 2, 5, 10]),
    st.integers(0, 2**31 - 1),
)
def test_compiled_projection_with_an_extra_row_matches_numpy(n, drop, eps, stall, seed):
    """As the dimension test's probes project (stall > 0: giving up once the residual stalls):
    both backends decide alike, and where they converge they agree."""
    x0, keep, free, _, rng = _perturbed_problem(n, drop, eps, seed)
    v = rng.standard_normal(free.size)
    extra = (v[None, :], np.array([v @ x0[free]]))
    kw = dict(tol=P.tol, dx_max=P.dx_max, max_iter=P.newton_max_iter, extra=extra, stall=stall)
    with kernels.backend("numba"):
        a = kernels.project(x0, keep, free, **kw)
    with kernels.backend("numpy"):
        b = kernels.project(x0, keep, free, **kw)
    assert a.ok == b.ok
    if a.ok:
        assert abs(v @ a.x[free] - extra[1][0]) < 1e-7
        assert np.abs(a.x - b.x).max() < 1e-9


@settings(max_examples=25, deadline=None, derandomize=True)
@given(st.integers(5, 12), st.integers(1, 3), st.floats(1e-4, 1e-2), st.integers(0, 2**31 - 1))
def test_compiled_projection_is_equivariant_under_relabelling(n, drop, eps, seed):
    x0, keep, free, tri, rng = _perturbed_problem(n, drop, eps, seed)
    perm = rng.permutation(n)
    inv = np.argsort(perm)
    xp = x0.reshape(-1, 3)[perm].ravel()
    kp = inv[keep]
    freep = kernels.free_coordinates(n, tuple(int(inv[i]) for i in tri))
    kw = dict(tol=P.tol, dx_max=P.dx_max, max_iter=P.newton_max_iter)
    with kernels.backend("numba"):
        a = kernels.project(x0, keep, free, **kw)
        b = kernels.project(xp, kp, freep, **kw)
    assert a.ok and b.ok
    assert np.abs(a.x.reshape(-1, 3)[perm] - b.x.reshape(-1, 3)).max() < 1e-12


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.integers(5, 12), st.integers(1, 3), st.floats(0.0, 1e-2), st.integers(0, 2**31 - 1))
def test_tangent_projection_and_rank_certificate_match_the_svd(n, drop, eps, seed):
    x0, keep, free, _, rng = _perturbed_problem(n, drop, eps, seed)
    with kernels.backend("numba"):
        x = kernels.project(x0, keep, free, tol=P.tol, dx_max=P.dx_max, max_iter=P.newton_max_iter).x
    ns = kernels.null_spaces(x, keep, free, P.tol_n)
    mask = kernels.free_mask(x.size, free)
    guard = kernels.guard_threshold(P.tol_n)
    ws = _compiled._workspace(x.size, keep, 0)
    certified = _compiled._full_row_rank(x, keep, mask, guard, ws)
    flexes = None
    with kernels.backend("numba"):
        flexes = kernels.regular_flexes(x, keep, free, P.tol_n)
    if certified:
        assert flexes == ns.V.shape[1] == free.size - keep.shape[0]
        assert ns.W.shape[1] == 0
        t = rng.standard_normal(x.size) * mask
        tn = np.empty(x.size)
        _compiled._project_tangent(x, keep, mask, t, ws, tn)
        assert np.allclose(tn, ns.V @ (ns.V.T @ t), atol=1e-12)
    else:
        assert flexes is None
        assert ns.sigma.min() < np.sqrt(guard) * np.sqrt(keep.shape[0])  # the certificate fails only near rank loss
    with kernels.backend("numpy"):
        assert kernels.regular_flexes(x, keep, free, P.tol_n) is None  # the reference always takes the SVD


def _qr_and_lstsq(x, edges, free, A):
    """(whether the QR step was taken, its step, LAPACK's step) for the rows ``edges`` and ``A`` at x."""
    f = np.random.default_rng(0).standard_normal(edges.shape[0] + A.shape[0])
    qr, ls = np.full(x.size, np.nan), np.empty(x.size)
    taken = _compiled._qr_step(x, edges, free, A, f, qr)
    _compiled._lstsq_step(x, edges, free, A, f, ls)
    return taken, qr, ls


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.integers(5, 12), st.integers(0, 3), st.floats(0.0, 1e-2), st.integers(0, 3), st.integers(0, 2**31 - 1))
def test_the_qr_step_is_lapacks_least_squares_step(n, drop, eps, extra, seed):
    """Where J has full rank, well away from losing it, the QR step is LAPACK's minimum-norm step, with and
    without extra linear rows, and it moves no pinned coordinate: for full row rank (QR of J^T) to cond(J)
    times the rounding unit; for more rows than free columns and full column rank (QR of J, the unique
    least-squares step of an inconsistent system) to cond(J)^2 times it, as least squares itself is
    determined."""
    x0, keep, free, _, rng = _perturbed_problem(n, drop, eps, seed)
    A = np.zeros((extra, x0.size))
    A[:, free] = rng.standard_normal((extra, free.size))
    taken, qr, ls = _qr_and_lstsq(x0, keep, free, A)
    J = np.vstack([2.0 * kernels.rigidity_matrix(x0, keep)[:, free], A[:, free]])
    sv = np.linalg.svd(J, compute_uv=False)
    if sv.min() < 1e-10 * sv.max():
        assert not taken and np.isnan(qr).all()
        return
    assert taken
    pinned = np.setdiff1d(np.arange(x0.size), free)
    assert np.all(qr[pinned] == 0.0)
    cond = sv.max() / sv.min()
    bound = cond**2 if J.shape[0] > J.shape[1] else cond
    assert np.abs(qr - ls).max() <= 1e-13 * bound * max(1.0, np.abs(ls).max())


def test_the_qr_step_of_more_rows_than_columns_is_taken_where_j_has_full_column_rank():
    """A seed cluster's contacts and extra rows, more rows than free columns: J = [R; A] has full column rank,
    so the QR step is taken and is LAPACK's step.  The same with a probe's row (R's one flex v) at a pre-stress
    stable cluster (the isolation probe of the rigidity test, R itself rank deficient by one): taken too."""
    x0, keep, free, _, rng = _perturbed_problem(9, 0, 1e-3, 7)
    A = np.zeros((2, x0.size))
    A[:, free] = rng.standard_normal((2, free.size))
    assert keep.shape[0] + 2 > free.size
    taken, qr, ls = _qr_and_lstsq(x0, keep, free, A)
    assert taken and np.allclose(qr, ls, rtol=0, atol=1e-10)
    stressed = Cluster.from_dict(FIXTURES["n10_m24_prestress"])
    tri = contact_triangle(stressed.edges())
    x = kernels.to_frame(stressed.coords, tri).ravel()
    free = kernels.free_coordinates(stressed.n, tri)
    ns = kernels.null_spaces(x, stressed.edges(), free, P.tol_n)
    assert ns.V.shape[1] == 1 and ns.W.shape[1] == 1
    probe = np.zeros((1, x.size))
    probe[0, free] = ns.V[free, 0]
    assert stressed.m + 1 > free.size
    taken, qr, ls = _qr_and_lstsq(x, stressed.edges(), free, probe)
    assert taken and np.allclose(qr, ls, rtol=0, atol=1e-10)


def test_the_qr_step_defers_to_lapack_where_j_is_rank_deficient():
    """A row repeated (an exact self-stress), with fewer rows than free columns or with more: no QR step.  A
    hyperstatic cluster's 25 contacts, first-order rigid (full column rank), and 24 independent rows of
    them: the QR step, equal to LAPACK's.  A stored
    pre-stress stable cluster's 24 contacts, whose smallest singular value is about 1e-9 (their self-stress
    holds to the accuracy of the coordinates): both solvers keep it, and agree to cond(J) times the
    rounding unit."""
    c = Cluster.from_dict(FIXTURES["n10_m25_first-order"])
    tri = contact_triangle(c.edges())
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(c.n, tri)
    none = np.zeros((0, x.size))
    taken, qr, ls = _qr_and_lstsq(x, c.edges(), free, none)  # 25 rows, 24 columns
    assert taken and np.allclose(qr, ls, rtol=0, atol=1e-10)
    taken, qr, ls = _qr_and_lstsq(x, c.edges()[1:], free, none)
    assert taken and np.allclose(qr, ls, rtol=0, atol=1e-10)
    repeated = np.vstack([c.edges()[2:], c.edges()[2:3]])  # 24 rows, two of them the same
    assert not _qr_and_lstsq(x, repeated, free, none)[0]
    tall = np.vstack([c.edges()[2:], c.edges()[2:4]])  # 25 rows of rank 23
    assert not _qr_and_lstsq(x, tall, free, none)[0]
    stressed = Cluster.from_dict(FIXTURES["n10_m24_prestress"])
    tri = contact_triangle(stressed.edges())
    x = kernels.to_frame(stressed.coords, tri).ravel()
    free = kernels.free_coordinates(stressed.n, tri)
    sv = np.linalg.svd(kernels.rigidity_matrix(x, stressed.edges())[:, free], compute_uv=False)
    assert sv.min() < 1e-8
    taken, qr, ls = _qr_and_lstsq(x, stressed.edges(), free, none)
    assert taken and np.abs(qr - ls).max() <= 1e-13 * (sv.max() / sv.min()) * np.abs(ls).max()


def test_rank_certificate_refuses_dependent_rows():
    """Contacts of a hyperstatic cluster carry a self-stress: R_f R_f^T is singular and must not be certified."""
    c = Cluster.from_dict(FIXTURES["n10_m25_first-order"])
    tri = contact_triangle(c.edges())
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(c.n, tri)
    with kernels.backend("numba"):
        assert kernels.regular_flexes(x, c.edges(), free, P.tol_n) is None
        # one contact fewer: 24 independent rows, certified, and no flex (first-order rigid)
        assert kernels.regular_flexes(x, c.edges()[1:], free, P.tol_n) == 0


# --------------------------------------------------------------------------- (c) the numpy reference stays selectable


def test_numpy_backend_can_be_selected(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("compiled code called with the numpy backend")

    kernels.set_backend("numpy")
    assert kernels.get_backend() == "numpy" and not kernels.compiled()
    monkeypatch.setattr(_compiled, "newton", refuse)
    monkeypatch.setattr(_compiled, "follow_steps", refuse)
    monkeypatch.setattr(paths_module, "_follow_compiled", refuse)
    p = path_starts(seed_cluster(7), P)[0]
    end = follow_path(p.x, p.keep, p.broken, p.tangent, p.free, P)
    assert end.steps > 0
    assert warm_up() == 0.0


def test_backend_context_manager_restores_the_previous_backend():
    kernels.set_backend("numba")
    with kernels.backend("numpy") as name:
        assert name == "numpy" and kernels.get_backend() == "numpy"
        with kernels.backend("numba"):
            assert kernels.compiled()
        assert kernels.get_backend() == "numpy"
    assert kernels.get_backend() == "numba"
    with pytest.raises(ValueError):
        kernels.set_backend("fortran")
    with pytest.raises(ValueError):
        with kernels.backend("fortran"):
            pass
    assert kernels.get_backend() == "numba"


@pytest.mark.parametrize("value, expected", [(None, "numba"), ("numpy", "numpy"), ("NUMBA", "numba")])
def test_environment_variable_selects_the_backend(value, expected):
    env = {k: v for k, v in os.environ.items() if k != "PACKINGS_KERNELS"}
    if value is not None:
        env["PACKINGS_KERNELS"] = value
    out = subprocess.run(
        [sys.executable, "-c", "from packings.workers import kernels; print(kernels.get_backend())"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert out.stdout.strip() == expected


_SIGNATURES = """
import json, numba
from packings.workers import _compiled, kernels
from packings.workers.cluster import Cluster
from packings.workers.expand import expand, warm_up
from packings.workers.params import Params
from packings.workers.seeds import seed_cluster

def signatures():
    return {k: sorted(map(str, v.signatures)) for k, v in vars(_compiled).items()
            if isinstance(v, numba.core.registry.CPUDispatcher)}

kernels.set_backend("numba")
seconds = warm_up()
warm = signatures()
data = json.load(open("tests/data/clusters_n10.json"))
for c in [seed_cluster(8), Cluster.from_dict(data["n10_m23_prestress"]), Cluster.from_dict(data["n10_m25_first-order"])]:
    expand(c, Params())
print(json.dumps([seconds, warm, signatures()]))
"""


def test_warm_up_compiles_every_kernel_the_paths_use_and_reports_seconds():
    """In a fresh process, after warm_up, expanding clusters (a regular one, a hypostatic and a hyperstatic
    one) compiles nothing more: every kernel it calls has the signature the warm-up gave it."""
    out = subprocess.run(
        [sys.executable, "-c", _SIGNATURES], cwd=ROOT, capture_output=True, text=True, check=True, timeout=900
    )
    seconds, warm, after = json.loads(out.stdout.strip().splitlines()[-1])
    assert isinstance(seconds, float) and seconds >= 0.0
    assert any(warm.values()) and after == warm


def _stressed_problem(n, eps, seed, extra=0):
    """A seed cluster (perturbed as in _perturbed_problem) with one more row, the pair of apexes of two of its
    tetrahedra that share a face, so that those five spheres are all joined (a complete graph on five vertices
    has a self-stress at every position), and 1 + ``extra`` contacts fewer elsewhere, with ``extra`` random
    linear rows: J loses rank through a row that is a combination of others, wherever the point is."""
    x0, keep, free, tri, rng = _perturbed_problem(n, 0, eps, seed)
    adjacent = {tuple(e) for e in keep.tolist()} | {tuple(e[::-1]) for e in keep.tolist()}
    bipyramids = [
        (i, j, face)
        for i in range(n)
        for j in range(i + 1, n)
        if (i, j) not in adjacent
        for face in combinations([v for v in range(n) if (i, v) in adjacent and (j, v) in adjacent], 3)
        if all((a, b) in adjacent for a, b in combinations(face, 2))
    ]
    i, j, face = bipyramids[rng.integers(len(bipyramids))]
    five = {i, j, *face}
    held = set(combinations(sorted(tri), 2))
    removable = [k for k, (a, b) in enumerate(keep.tolist()) if not {a, b} <= five and (a, b) not in held]
    edges = np.vstack([np.delete(keep, rng.choice(removable, size=1 + extra, replace=False), axis=0), [[i, j]]])
    A = np.zeros((extra, x0.size))
    A[:, free] = rng.standard_normal((extra, free.size))
    return x0, edges, free, A


def _jacobian(x, edges, free, A):
    return np.vstack([2.0 * kernels.rigidity_matrix(x, edges)[:, free], A[:, free]])


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.integers(6, 12), st.floats(0.0, 1e-2), st.integers(0, 2), st.integers(0, 2**31 - 1))
def test_the_reduced_step_is_lapacks_step_where_a_stress_persists(n, eps, extra, seed):
    """Where a row of J is a combination of others at every point (five spheres all joined), J is rank deficient
    to rounding: no QR step, and the reduced step (two QR factorisations of full-rank matrices) is LAPACK's
    minimum-norm least-squares step, to cond(J)^2 times the rounding unit (cond over its nonzero singular values),
    and moves no pinned coordinate."""
    x0, edges, free, A = _stressed_problem(n, eps, seed, extra)
    J = _jacobian(x0, edges, free, A)
    sv = np.linalg.svd(J, compute_uv=False)
    rank = int(np.count_nonzero(sv > 1e-12 * sv[0]))
    assert rank < min(J.shape)  # the stress persists off the solution set
    f = np.random.default_rng(seed).standard_normal(J.shape[0])
    G = J @ J.T
    red, qr, ls = np.full(x0.size, np.nan), np.full(x0.size, np.nan), np.empty(x0.size)
    assert not _compiled._qr_step(x0, edges, free, A, f, qr)
    taken = _compiled._reduced_step(x0, edges, free, A, f, G, red)
    _compiled._lstsq_step(x0, edges, free, A, f, ls)
    if sv[rank - 1] < 1e-10 * sv[0]:  # not certified: the rows kept are themselves nearly dependent
        assert not taken and np.isnan(red).all()
        return
    assert taken
    pinned = np.setdiff1d(np.arange(x0.size), free)
    assert np.all(red[pinned] == 0.0)
    cond = sv[0] / sv[rank - 1]
    assert np.abs(red - ls).max() <= 1e-13 * cond**2 * max(1.0, np.abs(ls).max())


def test_the_reduced_step_defers_to_lapack_unless_the_dependence_is_at_rounding_level():
    """A stored pre-stress stable cluster's 24 contacts, whose smallest singular value is about 1e-9 (the stress
    holds only to the accuracy of the coordinates, not at every point): LAPACK keeps that singular value, so the
    reduced step, which would drop its row, is not taken.  Nor where no row is dependent (a regular seed), nor
    where the rows left have full column rank (a hyperstatic cluster's 25 contacts in 24 columns: QR's case)."""
    stressed = Cluster.from_dict(FIXTURES["n10_m24_prestress"])
    tri = contact_triangle(stressed.edges())
    x = kernels.to_frame(stressed.coords, tri).ravel()
    free = kernels.free_coordinates(stressed.n, tri)
    none = np.zeros((0, x.size))
    J = _jacobian(x, stressed.edges(), free, none)
    sv = np.linalg.svd(J, compute_uv=False)
    assert 1e-12 * sv[0] < sv.min() < 1e-7
    dx = np.full(x.size, np.nan)
    f = np.ones(J.shape[0])
    assert not _compiled._reduced_step(x, stressed.edges(), free, none, f, J @ J.T, dx)
    x0, keep, free0, _, _ = _perturbed_problem(9, 1, 1e-3, 3)
    J0 = _jacobian(x0, keep, free0, np.zeros((0, x0.size)))
    assert not _compiled._reduced_step(x0, keep, free0, np.zeros((0, x0.size)), np.ones(J0.shape[0]), J0 @ J0.T, dx)
    c = Cluster.from_dict(FIXTURES["n10_m25_first-order"])
    tri = contact_triangle(c.edges())
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(c.n, tri)
    J = _jacobian(x, c.edges(), free, none)
    assert J.shape[0] > J.shape[1]
    assert not _compiled._reduced_step(x, c.edges(), free, none, np.ones(J.shape[0]), J @ J.T, dx)
    assert np.isnan(dx).all()


@settings(max_examples=80, deadline=None, derandomize=True)
@given(
    st.booleans(),
    st.integers(6, 12),
    st.integers(0, 3),
    st.floats(0.0, 1e-2),
    st.integers(0, 3),
    st.integers(0, 2**31 - 1),
)
def test_a_newton_step_is_the_same_whichever_of_the_qr_and_reduced_steps_is_asked_first(
    stressed, n, drop, eps, extra, seed
):
    """Where the normal equations are refused, Newton's step asks the QR and the reduced steps in either order
    (the one that served the last step first). The two never both take a step (rows dependent to rounding leave
    J a singular value far below QR's bound), so the step is the same to the last bit in either order: the QR
    step where it is taken, else the reduced step, else LAPACK's; and the order then asks first the one taken.
    Problems with a persisting self-stress and without; with no extra row, a random one, repeated contacts
    (dependent everywhere), or a row within 1e-12 of a combination of the contacts' (nearly dependent: neither
    step is taken)."""
    if stressed:
        x0, edges, free, A = _stressed_problem(n, eps, seed, min(extra, 2))
    else:
        x0, edges, free, _, rng = _perturbed_problem(n, drop, eps, seed)
        if extra == 2:
            edges = np.vstack([edges, edges[: drop + 1]])
        A = np.zeros((int(extra in (1, 3)), x0.size))
        A[:, free] = rng.standard_normal((A.shape[0], free.size))
        if extra == 3:
            R = 2.0 * kernels.rigidity_matrix(x0, edges)[:, free]
            A[:, free] = rng.standard_normal(R.shape[0]) @ R + 1e-12 * np.linalg.norm(R) * A[:, free]
    f = np.random.default_rng(seed).standard_normal(edges.shape[0] + A.shape[0])
    mask = kernels.free_mask(x0.size, free)
    ws = _compiled._workspace(x0.size, edges, A.shape[0])
    ws[6][:] = f
    refused = 0
    for guard in (_compiled.NO_NORMAL, kernels.guard_threshold(P.tol_n)):  # the first refuses the normal equations
        for first in (0, 1):
            order = np.array([first])
            if _compiled._newton_step(x0, edges, free, mask, A, ws[6], guard, ws, order):
                continue
            refused += 1
            G = ws[4].copy()  # J J^T (up to a power of two) as the step computed it
            qr, red, ls = (np.full(x0.size, np.nan) for _ in range(3))
            took_qr = _compiled._qr_step(x0, edges, free, A, f, qr)
            took_reduced = _compiled._reduced_step(x0, edges, free, A, f, G, red)
            assert not (took_qr and took_reduced)
            _compiled._lstsq_step(x0, edges, free, A, f, ls)
            assert np.array_equal(ws[9], qr if took_qr else red if took_reduced else ls)
            assert order[0] == (0 if took_qr else 1 if took_reduced else first)
    assert refused >= 2


def _isolation_probes():
    """The projections of the isolation probe (packings.workers.rigidity.on_a_curve) at the pre-stress stable
    n = 10 fixtures, and at larger steps: (x0, edges, free, A, b), a row holding the correction orthogonal to
    the flex."""
    out = []
    for name, raw in FIXTURES.items():
        if "prestress" not in name:
            continue
        c = Cluster.from_dict(raw)
        edges = c.edges()
        tri = contact_triangle(edges)
        x = kernels.to_frame(c.coords, tri).ravel()
        free = kernels.free_coordinates(c.n, tri)
        V = kernels.null_spaces(x, edges, free, P.tol_n).V
        for j in range(V.shape[1]):
            vf = V[free, j]
            for eps in (4 * P.ds0, 2 * P.ds0, P.ds0, P.ds0 / 2):
                for sign in (1.0, -1.0):
                    x0 = x + sign * eps * V[:, j]
                    A = np.zeros((1, x.size))
                    A[0, free] = vf
                    out.append((x0, edges, free, A, np.array([vf @ x0[free]])))
    return out


def test_a_failure_after_normal_equations_is_redone_without_them_and_fails_as_lapacks_iteration_does():
    """A projection that fails after a normal-equation step is redone from its start with none: the QR or
    reduced step where certified, LAPACK's elsewhere (NO_NORMAL). Its verdict is that of LAPACK's least squares
    at every step (a guard of inf) and of the numpy reference; where they converge, to the same point."""
    guard = kernels.guard_threshold(P.tol_n)
    kw = (P.tol, P.dx_max, P.newton_max_iter, False)
    retried = 0
    for x0, edges, free, A, b in _isolation_probes():
        mask = kernels.free_mask(x0.size, free)
        x, status, _, _, normal, redone = _compiled.newton(x0, edges, free, mask, A, b, *kw, guard, P.probe_stall)
        ws = _compiled._workspace(x0.size, edges, 1)
        first = _compiled._newton_core(
            x0, edges, free, mask, A, b, *kw, guard, ws, P.probe_stall, np.zeros(1, np.int64)
        )
        assert redone == (first[1] == _compiled.NEWTON_FAILED and first[4] > 0)
        if not redone:
            continue
        retried += 1
        assert normal == first[4]  # the second pass took no normal-equation step
        again = _compiled._newton_core(
            x0, edges, free, mask, A, b, *kw, _compiled.NO_NORMAL, ws, P.probe_stall, np.zeros(1, np.int64)
        )
        assert again[4] == 0 and np.array_equal(again[0], x) and again[1] == status
        lapack = _compiled._newton_core(
            x0, edges, free, mask, A, b, *kw, np.inf, ws, P.probe_stall, np.zeros(1, np.int64)
        )
        with kernels.backend("numpy"):
            reference = kernels.project(x0, edges, free, extra=(A[:, free], b), stall=P.probe_stall, **P.newton())
        assert status == lapack[1] and (status == _compiled.NEWTON_OK) == reference.ok
        if reference.ok:
            assert np.abs(x - reference.x).max() < 1e-9
    assert retried >= 4


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.integers(6, 12), st.floats(0.0, 1e-2), st.integers(0, 2**31 - 1))
def test_the_reduced_tangent_is_the_svds_where_a_stress_persists(n, eps, seed):
    """The tangent of a path along which a self-stress persists (five spheres all joined, one contact fewer
    elsewhere): the projection of t onto the SVD's null space (singular values below
    tol_n), without the SVD; and where it cannot show that (the pre-stress stable cluster, whose smallest
    singular value is about 1e-9), -1 so that the SVD decides."""
    x0, edges, free, _ = _stressed_problem(n, eps, seed)
    rng = np.random.default_rng(seed)
    mask = kernels.free_mask(x0.size, free)
    guard = kernels.guard_threshold(P.tol_n)
    t = rng.standard_normal(x0.size) * mask
    ws = _compiled._workspace(x0.size, edges, 0)
    tn, ref = np.empty(x0.size), np.empty(x0.size)
    norm = _compiled._reduced_tangent(x0, edges, free, mask, t, guard, ws, tn)
    ref_norm = _compiled._svd_tangent(x0, edges, free, t, P.tol_n, ref)
    sv = np.linalg.svd(kernels.rigidity_matrix(x0, edges)[:, free], compute_uv=False)
    if norm < 0.0:  # refused: only where the rows kept are not certified far from rank loss
        assert sv[sv > 1e-12 * sv[0]].min() < 1e-2
        return
    assert abs(norm - ref_norm) <= 1e-9 and np.allclose(tn, ref, rtol=0, atol=1e-9)
    stressed = Cluster.from_dict(FIXTURES["n10_m24_prestress"])
    tri = contact_triangle(stressed.edges())
    x = kernels.to_frame(stressed.coords, tri).ravel()
    free = kernels.free_coordinates(stressed.n, tri)
    mask = kernels.free_mask(x.size, free)
    ws = _compiled._workspace(x.size, stressed.edges(), 0)
    t = rng.standard_normal(x.size) * mask
    assert _compiled._reduced_tangent(x, stressed.edges(), free, mask, t, guard, ws, np.empty(x.size)) == -1.0


# --------------------------------------------------------------------------- the triangular kernels, four rows at a time


def _cholesky_one_row(G):
    """The left-looking Cholesky one entry at a time, each sum in the order p = 0, 1, ... (plain Python floats:
    IEEE double arithmetic, the order written), or None where a pivot is not positive."""
    size = G.shape[0]
    L = [[0.0] * size for _ in range(size)]
    for j in range(size):
        s = float(G[j, j])
        for p in range(j):
            s -= L[j][p] * L[j][p]
        if not s > 0.0:
            return None
        L[j][j] = float(np.sqrt(s))
        for i in range(j + 1, size):
            t = float(G[i, j])
            for p in range(j):
                t -= L[i][p] * L[j][p]
            L[i][j] = t / L[j][j]
    return np.array(L)


def _forward_one_row(L, b, each, plus):
    """out[i] = (b[i] -/+ sum_{p < i} L'[i, p] out[p]) / L[i, i] one row at a time (L' = L, or |L| with ``plus``;
    b[i] = ``each`` for every i where b is None)."""
    out = []
    for i in range(L.shape[0]):
        s = each if b is None else float(b[i])
        for p in range(i):
            s = s + abs(L[i, p]) * out[p] if plus else s - L[i, p] * out[p]
        out.append(s / L[i, i])
    return np.array(out)


def _spd_problems():
    """Gram matrices R_f R_f^T of real contact graphs (sparse, as the path loop factors them), and random dense
    SPD matrices of every size up to 13 (every remainder of the four-row blocks)."""
    out = []
    for n in (6, 9, 12):
        c = seed_cluster(n, P)
        edges = c.edges()[1:]
        tri = contact_triangle(edges)
        x = kernels.to_frame(c.coords, tri).ravel()
        R = kernels.rigidity_matrix(x, edges)[:, kernels.free_coordinates(n, tri)]
        out.append(R @ R.T)
    rng = np.random.default_rng(5)
    for size in range(1, 14):
        A = rng.standard_normal((size, size + 3))
        out.append(A @ A.T)
    return out


@pytest.mark.parametrize("G", _spd_problems(), ids=lambda G: f"size{G.shape[0]}")
def test_the_four_row_triangular_kernels_are_the_one_row_loops_bit_for_bit(G):
    """_cholesky, _forward_solve and the two eigenvalue bounds take four rows through each inner loop at once,
    each row's sum in the one-row loop's order: their results are the one-row loops' to the last bit (so
    that no path, projection or certificate moves).  The factor must also be a Cholesky factor of G."""
    size = G.shape[0]
    L = np.full((size, size), np.nan)
    assert _compiled._cholesky(np.ascontiguousarray(G), L, size)
    ref = _cholesky_one_row(G)
    low = np.tril_indices(size)
    assert np.array_equal(L[low], ref[low])
    L = np.tril(L)
    assert np.allclose(L @ L.T, G, rtol=0, atol=1e-12 * np.abs(G).max())
    b = np.random.default_rng(size).standard_normal(size)
    out = np.empty(size)
    _compiled._forward_solve(L, size, b, out)
    assert np.array_equal(out, _forward_one_row(L, b, None, False))
    inplace = b.copy()
    _compiled._forward_solve(L, size, inplace, inplace)  # b may be out
    assert np.array_equal(inplace, out)
    z = _forward_one_row(L, None, 1.0, True)  # M z = e for the comparison matrix M of L
    w = np.ones(size)
    for i in range(size - 1, -1, -1):  # M^T w = e, one row at a time
        s = 1.0
        for p in range(i + 1, size):
            s += abs(L[p, i]) * w[p]
        w[i] = s / L[i, i]
    assert _compiled._comparison_lower_bound(L, size, np.empty(size)) == 1.0 / (z.max() * w.max())
    total = 0.0  # ||L^-1||_F^2, column by column, one row at a time
    for j in range(size):
        u = [0.0] * size
        for i in range(j, size):
            s = 1.0 if i == j else 0.0
            for p in range(j, i):
                s -= L[i, p] * u[p]
            u[i] = s / L[i, i]
            total += u[i] * u[i]
    assert _compiled._eig_lower_bound(L, size, np.empty(size)) == 1.0 / total


def test_cholesky_refuses_a_matrix_that_is_not_positive_definite():
    """A zero pivot in any position of the four-row blocks, and a nan, stop the factorisation."""
    rng = np.random.default_rng(1)
    for size in (3, 6, 9):
        A = rng.standard_normal((size, size - 1))  # rank size - 1: a zero pivot (to rounding) or a negative one
        G = A @ A.T
        G[-1, -1] -= abs(G).max()  # certainly not positive definite
        assert not _compiled._cholesky(G, np.zeros((size, size)), size)
        H = np.eye(size)
        H[size // 2, size // 2] = np.nan
        assert not _compiled._cholesky(H, np.zeros((size, size)), size)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(st.sampled_from(sorted(FIXTURES)), st.integers(0, 2**31 - 1), st.booleans())
def test_floppy_without_certifies_only_what_regular_flexes_certifies_after_to_frame(name, seed, reflect):
    """Every sphere of a test cluster of 10, moved and relabelled, deleted in turn: where floppy_without gives a
    number of flexes, regular_flexes of what is left, put in its triangle's frame by to_frame, gives the same
    (the SVD too), and it gives none where the pinned matrix has no flex; the numpy backend gives none."""
    from packings.workers.catalysis import sub_cluster

    c, _ = congruent_copy(Cluster.from_dict(FIXTURES[name]), seed, reflect)
    spheres, triangles, expected = [], [], []
    for s in range(c.n):
        r = sub_cluster(c, [i for i in range(c.n) if i != s])
        tri = contact_triangle(r.contacts)
        if tri is None:
            continue
        x = kernels.to_frame(r.coords, tri).ravel()
        free = kernels.free_coordinates(r.n, tri)
        with kernels.backend("numba"):
            expected.append(kernels.regular_flexes(x, r.edges(), free, P.tol_n))
        spheres.append(s)
        triangles.append(tri)
        ns = kernels.null_spaces(x, r.edges(), free, P.tol_n)
        expected[-1] = (expected[-1], ns.V.shape[1], ns.W.shape[1])
    with kernels.backend("numba"):
        got = kernels.floppy_without(c.coords, c.edges(), np.array(spheres), np.array(triangles), P.tol_n)
    assert len(got) == len(spheres) and (got > 0).any()
    for g, (certified, v, w) in zip(got.tolist(), expected):
        assert g == -1 or (g > 0 and certified == g == v and w == 0)
        if certified == 0:  # no flex left: the caller decides (first-order rigid, its root to be proved)
            assert g == -1
    with kernels.backend("numpy"):
        assert (
            kernels.floppy_without(c.coords, c.edges(), np.array(spheres), np.array(triangles), P.tol_n) == -1
        ).all()
