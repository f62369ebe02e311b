"""Dimension of the solution set: the regular (rank) branch and the numerical estimate."""

import functools
import json
from collections import Counter
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest

from packings.workers import dimension, kernels
from packings.workers.cluster import Cluster
from packings.workers.dimension import solution_dimension
from packings.workers.params import Params
from packings.workers.rigidity import contact_triangle
from packings.workers.seeds import seed_cluster

P = Params()
FIXTURES = json.loads((Path(__file__).parents[1] / "data" / "clusters_n10.json").read_text())


def _set_left(c: Cluster, idx=()):
    """(x, contacts kept, free coordinates, null spaces) of ``c`` with the contacts ``idx`` deleted, in the
    frame of the first triangle left."""
    keep = np.delete(c.edges(), list(idx), axis=0)
    tri = contact_triangle(keep)
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(c.n, tri)
    return x, keep, free, kernels.null_spaces(x, keep, free, P.tol_n)


def dim_after_breaking(c: Cluster, idx):
    x, keep, free, ns = _set_left(c, idx)
    return solution_dimension(x, keep, free, P, ns), x, keep


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


def _numerical_cases(c: Cluster, size: int):
    """(idx, x, keep, free) for every ``size``-subset of contacts of ``c`` whose dimension needs the numerical estimate."""
    for idx in combinations(range(c.m), size):
        x, keep, free, ns = _set_left(c, idx)
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
    for idx, x, keep, free in _numerical_cases(c, 2):
        a = solution_dimension(x, keep, free, P)
        b = solution_dimension(x, keep, free, full)
        assert (a.dim, a.method) == (b.dim, b.method), idx
        assert np.allclose(a.tangents, b.tangents, atol=1e-9), idx
        dims.add(a.dim)
    assert {1, 2} <= dims


def test_a_limit_stops_probing_above_it_and_keeps_the_first_directions():
    c = Cluster.from_dict(FIXTURES["n10_m24_prestress"])
    seen = set()
    for idx, x, keep, free in _numerical_cases(c, 2):
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
    for idx, x, keep, free in _numerical_cases(c, 2):
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
    idx, x, keep, free = next(_numerical_cases(c, 2))
    v = kernels.null_spaces(x, keep, free, P.tol_n).V[:, 0]
    assert dimension.orthogonal_may_be_accepted(x + P.ds0 * v, keep, P.ds0, 1.0, loose)
    # and a stricter one than the probe step never accepts it
    assert not dimension.orthogonal_may_be_accepted(x + P.ds0 * v, keep, P.ds0, 1.0, P.with_(x_tol_max=0.9 * P.ds0))


# ----------------------------------------------------------------- first-order counts from the self-stresses

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from packings.workers.dimension import StressBasis, counts_after_breaking, may_decide  # noqa: E402
from packings.workers.expand import PathStart, _attempts  # noqa: E402


def _svd_counts(c: Cluster, idx):
    """(flexes, stresses) after deleting ``idx``, by an SVD of what is left, in that frame."""
    keep = np.delete(c.edges(), list(idx), axis=0)
    tri = contact_triangle(keep)
    x = kernels.to_frame(c.coords, tri).ravel()
    ns = kernels.null_spaces(x, keep, kernels.free_coordinates(c.n, tri), P.tol_n)
    return ns.V.shape[1], ns.W.shape[1], tri


def _basis(c: Cluster, tri) -> StressBasis:
    x = kernels.to_frame(c.coords, tri).ravel()
    return StressBasis.of(kernels.null_spaces(x, c.edges(), kernels.free_coordinates(c.n, tri), P.tol_n), P.tol_n)


@pytest.mark.parametrize("name", sorted(FIXTURES))
def test_the_first_order_counts_decide_every_subset_as_the_svd_does(name):
    """Every attempt of a cluster (regular, hyperstatic, pre-stress stable, hypostatic) is the same whether
    the subsets whose first-order count decides them are decided from the cluster's self-stresses or
    each by an SVD of what is left: same outcomes and dimensions in the same order, and the same
    directions followed from each subset.  Where the count is one flex and no stress the tangent comes
    from the cluster's own SVD: its sign (hence the direction label) may differ, and the direction
    agrees to the accuracy of the stored coordinates (1e-8 where a stress holds only to that)."""
    c = Cluster.from_dict(FIXTURES[name])
    fast, slow = list(_attempts(c, P, first_order=True)), list(_attempts(c, P, first_order=False))
    assert [type(a) for a in fast] == [type(b) for b in slow]
    assert [a for a in fast if not isinstance(a, PathStart)] == [b for b in slow if not isinstance(b, PathStart)]
    starts = {}
    for a in slow:
        if isinstance(a, PathStart):
            starts.setdefault(a.broken_contacts, []).append(a.tangent)
    for a in fast:
        if isinstance(a, PathStart):
            assert min(np.abs(a.tangent - t).max() for t in starts[a.broken_contacts]) < 1e-7
    assert sum(isinstance(a, PathStart) for a in fast) == sum(map(len, starts.values()))


def test_the_first_order_counts_equal_an_svd_of_what_is_left():
    """On the hyperstatic and the singular clusters, for every subset of one or two contacts whose count
    the self-stresses give, it is the SVD's; and they give it for most subsets."""
    given_, asked = 0, 0
    for name in ("n10_m25_first-order", "n10_m24_prestress", "n10_m23_prestress"):
        c = Cluster.from_dict(FIXTURES[name])
        bases = {}
        for k in (1, 2):
            for idx in combinations(range(c.m), k):
                f, s, tri = _svd_counts(c, idx)
                basis = bases.setdefault(tri, _basis(c, tri))
                counts = counts_after_breaking(basis, idx, P.tol_n)
                asked += 1
                if counts is not None:
                    given_ += 1
                    assert counts == (f, s), (name, idx)
    assert given_ > 0.9 * asked


def _moved(c: Cluster, idx, rnd):
    """(c with its spheres relabelled at random, rotated and maybe reflected; the indices of the contacts
    ``idx`` in it; the relabelling, old sphere -> new)."""
    from scipy.spatial.transform import Rotation

    perm = list(range(c.n))
    rnd.shuffle(perm)
    q = Rotation.random(random_state=rnd.randint(0, 2**32 - 1)).as_matrix() * rnd.choice([1.0, -1.0])
    moved_coords = np.empty_like(c.coords)
    moved_coords[perm] = c.coords @ q.T
    moved = Cluster(moved_coords, tuple(sorted((min(perm[i], perm[j]), max(perm[i], perm[j])) for i, j in c.contacts)))
    broken = {tuple(sorted((perm[i], perm[j]))) for i, j in (c.contacts[t] for t in idx)}
    return moved, [t for t, e in enumerate(moved.contacts) if e in broken], perm


@settings(max_examples=25, deadline=None)
@given(st.sampled_from(sorted(FIXTURES)), st.integers(1, 3), st.randoms(use_true_random=False))
def test_the_first_order_counts_do_not_depend_on_labels_or_orientation(name, k, rnd):
    """Relabel the spheres, rotate and reflect the cluster: the counts after deleting the same contacts
    (under the relabelling) are the same, and they are the SVD's."""
    c = Cluster.from_dict(FIXTURES[name])
    idx = sorted(rnd.sample(range(c.m), k))
    moved, moved_idx, _ = _moved(c, idx, rnd)
    results = []
    for cl, ix in ((c, idx), (moved, moved_idx)):
        f, s, tri = _svd_counts(cl, ix)
        if tri is None:
            return
        counts = counts_after_breaking(_basis(cl, tri), ix, P.tol_n)
        assert counts in (None, (f, s))
        results.append((f, s))
    assert results[0] == results[1]


def test_the_counts_defer_to_the_svd_near_tol_n():
    """A singular value of R, or of the stresses' rows, within the guard factor of tol_n: no count."""
    W = np.array([[1.0], [0.0], [0.0]])
    sure = StressBasis(W, flexes=0, smallest=1.0, largest=2.0, noise=1e-12)
    assert counts_after_breaking(sure, [0], P.tol_n) == (0, 0)  # the stress's contact: rigid, no stress left
    assert counts_after_breaking(sure, [1], P.tol_n) == (1, 1)  # a contact no stress uses: a flex, the stress
    assert counts_after_breaking(StressBasis(W, 0, 1.0, 2.0, noise=3e-7), [0], P.tol_n) is None
    assert counts_after_breaking(StressBasis(W, 0, smallest=5e-6, largest=2.0, noise=0.0), [0], P.tol_n) is None
    faint = StressBasis(np.array([[2e-6], [1.0], [0.0]]), 0, 1.0, 2.0, noise=0.0)
    assert counts_after_breaking(faint, [0], P.tol_n) is None  # 2e-6: between tol_n / 10 and 10 tol_n


def test_which_subset_sizes_the_counts_can_decide():
    regular_one_stress = StressBasis(np.zeros((25, 1)), 0, 1.0, 2.0, 0.0)
    assert may_decide(regular_one_stress, 1)  # the stress's contact: rigid
    singular = StressBasis(np.zeros((24, 1)), 1, 1.0, 2.0, 0.0)
    assert not may_decide(singular, 1)  # a flex and a stress, or two flexes and the stress: never decided
    assert may_decide(singular, 2)  # two flexes and no stress


def _frame(c: Cluster, tri=None):
    tri = tri or contact_triangle(c.edges())
    return kernels.to_frame(c.coords, tri).ravel(), kernels.free_coordinates(c.n, tri), tri


@pytest.mark.parametrize("name", sorted(FIXTURES))
def test_the_tangent_from_the_clusters_svd_is_the_null_vector_of_what_is_left(name):
    """For every subset of up to s + 1 contacts (s self-stresses) whose count is one flex and no stress:
    a unit vector, zero at the pinned coordinates, in the null space of R without B, and the tangent of
    solution_dimension up to sign.  There are such subsets wherever s + 1 - f >= 1 (not for the hypostatic
    fixture: f = 2, s = 1)."""
    c = Cluster.from_dict(FIXTURES[name])
    x, free, tri = _frame(c)
    basis = _basis(c, tri)
    R = kernels.rigidity_matrix(x, c.edges())
    pinned = np.setdiff1d(np.arange(x.size), free)
    found = 0
    for k in range(1, basis.W.shape[1] + 2):
        for idx in combinations(range(c.m), k):
            t = dimension.tangent_after_breaking(basis, idx, P.tol_n)
            counts = counts_after_breaking(basis, idx, P.tol_n)
            if counts != (1, 0):
                assert t is None
                continue
            found += 1
            assert np.isclose(np.linalg.norm(t), 1.0) and np.all(t[pinned] == 0.0)
            assert np.abs(np.delete(R, list(idx), axis=0) @ t).max() < 1e-8
            keep = np.delete(c.edges(), list(idx), axis=0)
            d = solution_dimension(x, keep, free, P)
            assert d.dim == 1 and d.method == "regular" and abs(abs(d.tangents[:, 0] @ t) - 1.0) < 1e-12
    assert (found > 0) == (basis.W.shape[1] + 1 - basis.flexes >= 1)


def test_the_tangent_defers_to_the_svd_near_tol_n():
    """A singular value of R within the guard factor of tol_n: no tangent (the SVD of what is left decides)."""
    c = Cluster.from_dict(FIXTURES["n10_m24_first-order"])
    x, free, tri = _frame(c)
    smallest = np.linalg.svd(kernels.rigidity_matrix(x, c.edges())[:, free], compute_uv=False).min()
    for tol_n, given_ in ((smallest / 5, False), (smallest / 20, True)):
        basis = StressBasis.of(kernels.null_spaces(x, c.edges(), free, tol_n), tol_n)
        assert (dimension.tangent_after_breaking(basis, [3], tol_n) is not None) == given_


@settings(max_examples=20, deadline=None, derandomize=True)
@given(st.sampled_from(sorted(set(FIXTURES) - {"n10_m23_prestress"})), st.randoms(use_true_random=False))
def test_the_tangent_does_not_depend_on_labels_or_orientation(name, rnd):
    """Relabel the spheres, rotate and reflect the cluster: breaking the same contacts (under the
    relabelling) opens the same motion.  The rate of change of every pair's squared distance along the
    tangent (the same in every pinned frame) agrees, up to the tangent's sign and length."""
    c = Cluster.from_dict(FIXTURES[name])
    basis = _basis(c, contact_triangle(c.edges()))
    k = basis.W.shape[1] + 1 - basis.flexes
    subsets = [idx for idx in combinations(range(c.m), k) if counts_after_breaking(basis, idx, P.tol_n) == (1, 0)]
    idx = rnd.choice(subsets)
    moved, moved_idx, perm = _moved(c, idx, rnd)
    strains = []
    for cl, ix, order in ((c, idx, list(range(c.n))), (moved, moved_idx, perm)):
        x, free, tri = _frame(cl)
        t = dimension.tangent_after_breaking(_basis(cl, tri), ix, P.tol_n)
        p, v = x.reshape(-1, 3)[order], t.reshape(-1, 3)[order]
        dp, dv = p[:, None] - p[None], v[:, None] - v[None]
        s = np.einsum("ijk,ijk->ij", dp, dv)
        strains.append(s / np.abs(s).max())
    a, b = strains
    assert min(np.abs(a - b).max(), np.abs(a + b).max()) < 1e-7


def test_without_a_self_stress_the_counts_are_read_off_at_once():
    """No self-stress (a regular cluster): deleting k rows leaves k flexes and no stress, and the tangent
    of a single break is the column of R's pseudo-inverse, as the general route through W_B gives it."""
    c = Cluster.from_dict(FIXTURES["n10_m24_first-order"])
    basis = _basis(c, contact_triangle(c.edges()))
    assert (basis.W.shape[1], basis.flexes) == (0, 0)
    for k in (1, 2, 3):
        assert counts_after_breaking(basis, list(range(k)), P.tol_n) == (basis.flexes + k, 0)
    t = dimension.tangent_after_breaking(basis, [2], P.tol_n)
    col = basis.pinv[:, 2]
    assert np.array_equal(t, col / np.linalg.norm(col)) or np.array_equal(t, -col / np.linalg.norm(col))
    unsure = StressBasis(basis.W, basis.flexes, basis.smallest, basis.largest, noise=P.tol_n)  # noise too near tol_n
    assert counts_after_breaking(unsure, [0], P.tol_n) is None


# ----------------------------------------------------------------- self-stresses held by a rigid part

from packings.workers.dimension import SUPPORT_NONZERO, SUPPORT_ZERO, rigid_part  # noqa: E402


def _hinged(c: Cluster) -> Cluster:
    """``c`` with one more sphere touching the two spheres of one contact and nothing else: a hinge,
    free to swing about that contact's axis while ``c`` stays as it is (one flex), ``c``'s self-stresses
    untouched."""
    p = c.coords
    centre = p.mean(axis=0)
    for a, b in c.contacts:
        u = (p[b] - p[a]) / np.linalg.norm(p[b] - p[a])
        mid = (p[a] + p[b]) / 2
        out = (mid - centre) - ((mid - centre) @ u) * u
        if np.linalg.norm(out) < 1e-3:
            continue
        q = mid + np.sqrt(0.75) * out / np.linalg.norm(out)
        others = np.delete(np.linalg.norm(p - q, axis=1), [a, b])
        if others.min() > 1.05:
            return Cluster(np.vstack([p, q]), tuple(sorted(c.contacts + ((a, c.n), (b, c.n)))))
    raise AssertionError("no contact to hinge a sphere on")


def test_a_stress_in_a_rigid_part_gives_the_dimension_without_probes(monkeypatch):
    """A hyperstatic cluster (a self-stress) with a sphere hinged on one of its contacts: the set is the
    hinge's circle, one-dimensional and smooth.  The stress lies in the hyperstatic cluster, an
    infinitesimally rigid part, so the dimension is |V| = 1 with V's tangent ("rigid-part"), which moves the
    hinged sphere alone, about its two contacts; the probes, asked instead, find one dimension too along
    the same direction.  With one of the hinge's contacts broken too it rolls: two dimensions."""
    c = _hinged(Cluster.from_dict(FIXTURES["n10_m25_first-order"]))
    x, keep, free, ns = _set_left(c)
    assert ns.W.shape[1] == 1 and ns.V.shape[1] == 1
    part = rigid_part(x, keep, StressBasis.of(ns, P.tol_n), P.tol_n)
    assert part is not None and c.n - 1 not in part and len(part) == c.n - 1
    d = solution_dimension(x, keep, free, P, limit=1)
    assert (d.dim, d.method) == (1, "rigid-part")
    t = d.tangents[:, 0].reshape(-1, 3)
    assert np.abs(t[:-1]).max() < 1e-10  # only the hinged sphere moves
    hinge = [i for i, j in c.contacts if j == c.n - 1]
    p = x.reshape(-1, 3)
    assert all(abs((p[-1] - p[i]) @ t[-1]) < 1e-10 for i in hinge)
    monkeypatch.setattr(dimension, "rigid_part", lambda *a, **k: None)
    probed = solution_dimension(x, keep, free, P, limit=1)
    assert (probed.dim, probed.method) == (1, "numerical")
    assert abs(probed.tangents[:, 0] @ d.tangents[:, 0]) > 0.99
    monkeypatch.undo()
    rolling = [k for k, (i, j) in enumerate(c.contacts) if j == c.n - 1][:1]
    x, keep, free, ns = _set_left(c, rolling)
    d = solution_dimension(x, keep, free, P, limit=1)
    assert (d.dim, d.method) == (2, "rigid-part") and not d.at_least


def test_an_endpoint_whose_stress_lies_in_a_rigid_part_is_floppy(monkeypatch):
    """The hinged cluster as an endpoint (every contact kept): one flex, one self-stress, the stress in
    the hyperstatic part.  Its pre-stress form vanishes on the hinge, so the pre-stress test alone leaves
    it undecided; the certificate proves it floppy (a circle of solutions)."""
    from packings.workers import paths
    from packings.workers.rigidity import Rigidity

    c = _hinged(Cluster.from_dict(FIXTURES["n10_m25_first-order"]))
    x, keep, free, ns = _set_left(c)
    assert (ns.V.shape[1], ns.W.shape[1]) == (1, 1)
    rig = paths.endpoint_rigidity(x, c.contacts, free, P)
    assert (rig.rigid, rig.kind, rig.method, rig.flexes, rig.stresses) == (False, "floppy", "rigid-part", 1, 1)
    monkeypatch.setattr(paths, "rigid_part", lambda *a, **k: None)
    before = paths.endpoint_rigidity(x, c.contacts, free, P)
    assert (before.rigid, before.kind) == (False, "undecided")
    monkeypatch.undo()
    found = Rigidity(False, "undecided", 1, 1, before.method, before.margin)
    assert paths._held_by_a_rigid_part(found, x, keep, ns, P.tol_n)
    in_doubt = Rigidity(
        False, "undecided", 1, 1, "unresolved", 2 * P.tol_psd
    )  # a margin the coordinates leave in doubt
    assert not paths._held_by_a_rigid_part(in_doubt, x, keep, ns, P.tol_n)


def test_a_stress_in_a_rigid_part_is_followed_along_a_smooth_curve():
    """Where the certificate holds, the set is a curve tangent to V: points projected from x + h v lie
    h v away to second order in h."""
    c = _hinged(Cluster.from_dict(FIXTURES["n10_m25_first-order"]))
    x, keep, free, ns = _set_left(c)
    v = solution_dimension(x, keep, free, P).tangents[:, 0]
    for h in (1e-2, 1e-3):
        pr = kernels.project(x + h * v, keep, free, **P.newton())
        assert pr.ok
        off = (pr.x - x) - ((pr.x - x) @ v) * v
        assert np.linalg.norm(off) < 5 * h * h


def test_no_rigid_part_where_a_count_or_the_support_is_in_doubt():
    """A singular value of R within the guard factor of tol_n, or a row of W between SUPPORT_ZERO and
    SUPPORT_NONZERO: no rigid part (the probes decide)."""
    c = _hinged(Cluster.from_dict(FIXTURES["n10_m25_first-order"]))
    x, keep, free, ns = _set_left(c)
    assert rigid_part(x, keep, StressBasis.of(ns, P.tol_n), P.tol_n) is not None
    sigma = ns.sigma.copy()
    sigma[np.argmin(np.where(sigma >= P.tol_n, sigma, np.inf))] = 5 * P.tol_n
    assert rigid_part(x, keep, StressBasis.of(kernels.NullSpaces(sigma, ns.V, ns.W), P.tol_n), P.tol_n) is None
    W = ns.W.copy()
    outside = int(np.argmin(np.abs(W[:, 0])))
    assert abs(W[outside, 0]) <= SUPPORT_ZERO
    W[outside, 0] = np.sqrt(SUPPORT_ZERO * SUPPORT_NONZERO)
    assert rigid_part(x, keep, StressBasis.of(kernels.NullSpaces(ns.sigma, ns.V, W), P.tol_n), P.tol_n) is None


def test_a_pre_stress_spread_over_the_cluster_is_held_by_no_rigid_part():
    """The singular n = 10 cluster's stress is its own pre-stress: with two contacts broken, where it
    persists it is held by no rigid part, and the probes decide (one and two dimensions)."""
    c = Cluster.from_dict(FIXTURES["n10_m24_prestress"])
    dims = set()
    for idx, x, keep, free in _numerical_cases(c, 2):
        assert (
            rigid_part(x, keep, StressBasis.of(kernels.null_spaces(x, keep, free, P.tol_n), P.tol_n), P.tol_n) is None
        ), idx
        dims.add(solution_dimension(x, keep, free, P, limit=1).dim)
    assert {1, 2} <= dims


@settings(max_examples=15, deadline=None, derandomize=True)
@given(st.randoms(use_true_random=False))
def test_a_rigid_part_does_not_depend_on_labels_or_orientation(rnd):
    """Relabel, rotate and reflect the hinged cluster: the same rigid part (relabelled) and dimension, and
    as an endpoint the same verdict."""
    from packings.workers.paths import endpoint_rigidity

    c = _hinged(Cluster.from_dict(FIXTURES["n10_m25_first-order"]))
    moved, _, perm = _moved(c, [], rnd)
    parts = []
    for cl in (c, moved):
        x, keep, free, ns = _set_left(cl)
        parts.append(rigid_part(x, keep, StressBasis.of(ns, P.tol_n), P.tol_n))
        assert solution_dimension(x, keep, free, P, limit=1).dim == 1
        assert endpoint_rigidity(x, cl.contacts, free, P).method == "rigid-part"
    assert parts[0] is not None and parts[1] is not None
    assert sorted(perm[i] for i in parts[0]) == sorted(parts[1].tolist())


def _held_path(c: Cluster):
    """(x, keep, free, the rigid-part dimension) of the hinged cluster with nothing broken: one flex, the
    hinge's circle, one self-stress in the hyperstatic part."""
    x, keep, free, ns = _set_left(c)
    return x, keep, free, solution_dimension(x, keep, free, P, ns, limit=1)


@settings(max_examples=10, deadline=None, derandomize=True)
@given(st.randoms(use_true_random=False))
def test_held_rows_leave_full_row_rank_and_the_same_curve(rnd):
    """The rows a rigid part holds (:func:`dimension.held_rows`): one per self-stress, each in the stress's
    support; without them R has full row rank (its smallest singular value far above tol_n) and the same
    null space, the curve's tangent, whatever the labels and orientation."""
    c = _hinged(Cluster.from_dict(FIXTURES["n10_m25_first-order"]))
    for cl in (c, _moved(c, [], rnd)[0]):
        x, keep, free, d = _held_path(cl)
        ns = kernels.null_spaces(x, keep, free, P.tol_n)
        assert (d.dim, d.method) == (1, "rigid-part") and d.held_rows is not None
        assert len(d.held_rows) == ns.W.shape[1] == 1
        assert np.all(np.linalg.norm(ns.W[d.held_rows], axis=1) >= SUPPORT_NONZERO)
        rest = kernels.null_spaces(x, np.delete(keep, d.held_rows, axis=0), free, P.tol_n)
        assert rest.W.shape[1] == 0 and rest.sigma.min() > 100 * P.tol_n
        assert rest.V.shape[1] == 1 and abs(rest.V[:, 0] @ d.tangents[:, 0]) > 1 - 1e-12


def test_no_held_rows_where_the_count_without_them_is_in_doubt():
    """A singular value of R near tol_n: the count after deleting the rows is not certain, so no rows are
    held and the path steps on every contact."""
    c = _hinged(Cluster.from_dict(FIXTURES["n10_m25_first-order"]))
    x, keep, free, ns = _set_left(c)
    assert dimension.held_rows(StressBasis.of(ns, P.tol_n), P.tol_n) is not None
    sigma = ns.sigma.copy()
    sigma[np.argmin(np.where(sigma >= P.tol_n, sigma, np.inf))] = 5 * P.tol_n
    assert dimension.held_rows(StressBasis.of(kernels.NullSpaces(sigma, ns.V, ns.W), P.tol_n), P.tol_n) is None
    assert (
        dimension.held_rows(
            StressBasis.of(kernels.null_spaces(*_set_left(seed_cluster(9))[:3], P.tol_n), P.tol_n), P.tol_n
        )
        is None
    )


@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_a_path_on_a_rigid_part_steps_on_the_rest_to_the_same_end(backend, monkeypatch):
    """The hinge swings until it touches a sphere: with the held row left out of the steps, the compiled
    loop hands no step to the SVD in Python (the rank guard certifies its first step) and the reference
    steps on the rest, and the path takes the same steps and ends at the same cluster, the held contact
    still a contact; with every contact the first step needs the SVD's tangent."""
    from packings.workers import paths

    if backend == "numpy":
        monkeypatch.setattr(kernels, "compiled", lambda: False)
    c = _hinged(Cluster.from_dict(FIXTURES["n10_m25_first-order"]))
    x, keep, free, d = _held_path(c)
    svds = []
    real = paths._svd_tangent
    monkeypatch.setattr(paths, "_svd_tangent", lambda xn, edges, *a: svds.append(len(edges)) or real(xn, edges, *a))
    ends = {}
    for held in (None, d.held_rows):
        svds.clear()
        for sign in (1.0, -1.0):
            ends[held is None, sign] = paths.follow_path(x, keep, keep[:0], sign * d.tangents[:, 0], free, P, held)
        ends[held is None] = list(svds)
    # with every contact: each step of the reference, the first step of the compiled loop
    assert ends[True] and all(m == len(keep) for m in ends[True])
    if backend == "compiled":
        assert ends[False] == []
    else:
        assert ends[False] and all(m == len(keep) - 1 for m in ends[False])
    held_pair = tuple(int(v) for v in keep[d.held_rows[0]])
    for sign in (1.0, -1.0):
        a, b = ends[False, sign], ends[True, sign]
        assert (a.outcome, a.steps, a.contacts, a.new_contacts) == (b.outcome, b.steps, b.contacts, b.new_contacts)
        assert a.outcome in ("rigid", "floppy", "undecided") and held_pair in a.contacts
        assert np.abs(a.coords - b.coords).max() < 1e-8


def _rigid_body_afresh(x, edges, inside, tol_n, guard):
    """The rigid-body test computed on the whole cluster's rigidity matrix, its columns of the part taken,
    as it was before :func:`dimension._rigid_body` remembered its answers."""
    spheres = np.nonzero(inside)[0]
    p = x.reshape(-1, 3)[spheres]
    if spheres.size < 3 or np.linalg.svd(p - p.mean(axis=0), compute_uv=False)[1] < 0.1:
        return None
    cols = (3 * spheres[:, None] + np.arange(3)).ravel()
    sv = np.linalg.svd(kernels.rigidity_matrix_numpy(x, edges)[:, cols], compute_uv=False)
    rank = 3 * spheres.size - 6
    ok = sv.size >= rank and dimension._separated(float(sv[rank - 1]), float(sv[rank:].max(initial=0.0)), guard, tol_n)
    return spheres if ok else None


def test_the_rigid_body_test_remembers_answers_without_changing_them():
    """The rigid-body test of a part asked again (the same coordinates and contacts) is answered from memory,
    and every answer, first or remembered, is the one computed afresh on the whole rigidity matrix: for the
    hyperstatic part of the hinged cluster (rigid), the part with the hinged sphere (not: it swings), a
    part in another frame, and three spheres in a row (collinear)."""
    c = _hinged(Cluster.from_dict(FIXTURES["n10_m25_first-order"]))
    x, keep, free, ns = _set_left(c)
    core = np.ones(c.n, dtype=bool)
    core[-1] = False
    every = np.ones(c.n, dtype=bool)
    cases = []
    for inside in (core, every):
        both = inside[keep[:, 0]] & inside[keep[:, 1]]
        cases.append((x, keep[both], inside))
    y = x.reshape(-1, 3).copy() @ np.linalg.qr(np.arange(9.0).reshape(3, 3) + np.eye(3))[0].T  # another frame
    both = core[keep[:, 0]] & core[keep[:, 1]]
    cases.append((y.ravel(), keep[both], core))
    line = np.zeros((c.n, 3))
    line[:3, 0] = [0.0, 1.0, 2.0]
    three = np.zeros(c.n, dtype=bool)
    three[:3] = True
    cases.append((line.ravel(), np.array([[0, 1], [1, 2]]), three))
    dimension._rigid_in_own_coordinates.cache_clear()
    for _ in range(2):
        for xx, ee, inside in cases:
            got = dimension._rigid_body(xx, ee, inside, P.tol_n, dimension.COUNT_GUARD)
            want = _rigid_body_afresh(xx, ee, inside, P.tol_n, dimension.COUNT_GUARD)
            assert (got is None) == (want is None)
            if got is not None:
                assert np.array_equal(got, want)
    assert [dimension._rigid_body(xx, ee, i, P.tol_n, dimension.COUNT_GUARD) is not None for xx, ee, i in cases] == [
        True,
        False,
        True,
        False,
    ]
    info = dimension._rigid_in_own_coordinates.cache_info()
    assert (info.misses, info.hits) == (len(cases), 2 * len(cases))  # each computed once, then remembered


# ----------------------------------------------------------------- what is left, read off the cluster's SVD

from packings.workers.rigidity import prestress_test, rigidity_from_null_spaces, stress_forms  # noqa: E402
from packings.workers.seeds import close_packed_seed  # noqa: E402


@pytest.fixture(scope="module")
def close_packed_12() -> Cluster:
    """The close-packed n = 12 seed: 32 contacts, two self-stresses; its broken subsets leave sets held by a
    rigid part, sets the pre-stress test finds rigid with one flex (``single-flex``) and with one stress
    (``single-stress``), and sets the probes decide."""
    return close_packed_seed(12)


def _projector(a: np.ndarray) -> np.ndarray:
    return a @ a.T


def _left(c: Cluster, idx):
    """(x, contacts kept, free coordinates, the cluster's StressBasis in that frame, what is left read off it,
    an SVD of what is left) for the contacts ``idx`` deleted, in the frame of the first triangle left."""
    x, keep, free, ns = _set_left(c, idx)
    tri = contact_triangle(keep)
    basis = _basis(c, tri)
    return x, keep, free, basis, dimension.left_after_breaking(basis, idx, P.tol_n), ns


def test_what_is_left_read_off_the_clusters_svd_is_what_its_own_svd_finds(close_packed_12):
    """For every subset of up to three contacts of the close-packed n = 12 cluster, and of up to two of the
    two singular fixtures: where the cluster's SVD gives V and W of what is left, they have the SVD's counts,
    span its spaces (projectors within 1e-8), are orthonormal, and bound its singular values (the nonzero
    ones from below, the zero ones from above, to rounding); and where a set is decided from them (a rigid part, or the
    pre-stress test's cheap cases), the SVD of the set decides it alike: the same dimension and method, the
    same tangent up to sign."""
    decided = Counter()
    cases = [(close_packed_12, 3)] + [
        (Cluster.from_dict(FIXTURES[nm]), 2) for nm in ("n10_m24_prestress", "n10_m23_prestress")
    ]
    for c, top in cases:
        for k in range(1, top + 1):
            for idx in combinations(range(c.m), k):
                x, keep, free, basis, left, ns = _left(c, idx)
                if left is None:
                    continue
                assert (left.flexes, left.W.shape[1]) == (ns.V.shape[1], ns.W.shape[1]), idx
                assert left.V.shape[1] == left.flexes
                assert np.abs(_projector(left.W) - _projector(ns.W)).max() < 1e-8
                assert np.abs(_projector(left.V) - _projector(ns.V)).max() < 1e-8
                assert np.abs(left.V.T @ left.V - np.eye(left.flexes)).max(initial=0.0) < 1e-10
                assert np.abs(left.W.T @ left.W - np.eye(left.W.shape[1])).max(initial=0.0) < 1e-10
                nonzero, zero = ns.sigma[ns.sigma >= P.tol_n], ns.sigma[ns.sigma < P.tol_n]
                rounding = 1e-13  # the SVDs' own, about eps |R|
                assert left.smallest <= nonzero.min() + rounding and left.noise >= zero.max(initial=0.0) - rounding
                assert left.largest >= ns.sigma.max() - rounding
                if not left.flexes or not left.W.shape[1]:
                    continue
                found = dimension._held_dimension(x, keep, left, P.tol_n) or dimension._rigid_by_left(keep, left, P)
                if found is None:
                    continue
                svd = solution_dimension(x, keep, free, P, ns, limit=1)
                assert (found.dim, found.method) == (svd.dim, svd.method), idx
                if found.dim == 1:
                    assert abs(abs(found.tangents[:, 0] @ svd.tangents[:, 0]) - 1.0) < 1e-10
                decided[found.rigidity.method if found.rigidity else found.method] += 1
    assert decided["rigid-part"] > 0 and decided["single-flex"] > 0 and decided["single-stress"] > 0, decided


def test_a_set_decided_from_what_is_left_takes_no_svd_of_it(close_packed_12, monkeypatch):
    """A set held by a rigid part, and one the pre-stress test finds rigid with one flex: with V and W read
    off the cluster's SVD, solution_dimension decides them without an SVD (it would fail here), as the SVD
    does; a set they leave to the probes takes the SVD as before."""
    cases = {idx: _left(close_packed_12, idx) for idx in ((1,), (0, 4), (2, 18))}
    svd = {idx: solution_dimension(x, keep, free, P, ns, limit=1) for idx, (x, keep, free, _, _, ns) in cases.items()}
    monkeypatch.setattr(kernels, "null_spaces", lambda *a, **k: pytest.fail("an SVD of the set was taken"))
    for idx, want in (((1,), (1, "rigid-part")), ((0, 4), (0, "rigid"))):
        x, keep, free, _, left, _ = cases[idx]
        d = solution_dimension(x, keep, free, P, limit=1, left=left)
        assert (d.dim, d.method) == (svd[idx].dim, svd[idx].method) == want
    monkeypatch.undo()
    x, keep, free, _, left, _ = cases[(2, 18)]
    assert dimension._held_dimension(x, keep, left, P.tol_n) is None and dimension._rigid_by_left(keep, left, P) is None
    d = solution_dimension(x, keep, free, P, limit=1, left=left)
    assert (d.dim, d.method) == (svd[(2, 18)].dim, svd[(2, 18)].method)


@functools.lru_cache(maxsize=1)
def _rigid_with_stresses():
    """(contacts kept, what is left) of the first 12 subsets of two contacts of the close-packed n = 14 seed
    (40 contacts) whose set the cheap cases find rigid from what is left with two or more stresses."""
    c = close_packed_seed(14)
    found = []
    for idx in combinations(range(c.m), 2):
        x, keep, free, basis, left, ns = _left(c, idx)
        if left is not None and left.flexes and left.W.shape[1] >= 2 and dimension._rigid_by_left(keep, left, P):
            found.append((keep, left))
            if len(found) == 12:
                return found
    raise AssertionError(f"only {len(found)} such subsets")


@settings(max_examples=25, deadline=None, derandomize=True)
@given(st.randoms(use_true_random=False))
def test_a_rigid_verdict_from_what_is_left_holds_in_every_basis_of_its_stresses(rnd):
    """The pre-stress test's verdict "rigid" on V and W read off the cluster's SVD is the test's verdict on
    any other orthonormal basis of the same stresses and flexes (an SVD's is one): rotate both at random
    (subsets of the close-packed n = 14 seed that leave one flex and two to four stresses),
    and the test, with its SDP, still finds the set rigid.  A margin below the guard's bound, sqrt(b) times
    tol_psd and more, is left to the SVD."""
    keep, left = rnd.choice(_rigid_with_stresses())
    rs = np.random.default_rng(rnd.randint(0, 2**31))
    b, a = left.W.shape[1], left.flexes
    cw = np.linalg.qr(rs.standard_normal((b, b)))[0]
    cv = np.linalg.qr(rs.standard_normal((a, a)))[0]
    rotated = kernels.NullSpaces(np.ones(1), left.V @ cv, left.W @ cw)
    assert rigidity_from_null_spaces(rotated, keep, P).rigid
    margin = prestress_test(stress_forms(left.V, left.W, keep), P.tol_psd)[2]
    near = Params(tol_psd=margin / (dimension.PRESTRESS_GUARD * np.sqrt(b)) * 1.01)  # margin < the bound
    assert prestress_test(stress_forms(left.V, left.W, keep), near.tol_psd)[0]  # rigid, but not by the guard
    assert dimension._rigid_by_left(keep, left, near) is None


def test_the_counts_read_in_batches_are_the_counts_read_one_by_one(close_packed_12, monkeypatch):
    """ranks_after_breaking gives, for every subset of two and of three contacts, the rank of W_B that
    counts_after_breaking counts (-1 where it gives None); and the attempts of a cluster whose counts are read
    in batches are those read one by one, to the bit (outcomes, directions, steps, endpoints)."""
    from packings.workers import expand

    for c in (close_packed_12, Cluster.from_dict(FIXTURES["n10_m23_prestress"])):
        basis = _basis(c, contact_triangle(c.edges()))
        for k in (2, 3):
            subsets = list(combinations(range(c.m), k))
            ranks = dimension.ranks_after_breaking(basis, subsets, P.tol_n)
            for idx, r in zip(subsets, ranks.tolist()):
                counts = counts_after_breaking(basis, idx, P.tol_n)
                assert counts == (None if r < 0 else (basis.flexes + k - r, basis.W.shape[1] - r)), idx
    unsure = StressBasis(basis.W, basis.flexes, basis.smallest, basis.largest, noise=P.tol_n)
    assert dimension.ranks_after_breaking(unsure, subsets, P.tol_n) is None

    def attempts(c):
        return [
            (
                e.broken,
                e.direction,
                e.outcome,
                e.steps,
                e.dim,
                e.new_contacts,
                None if e.cluster is None else e.cluster.coords.tobytes(),
            )
            for e in expand.expand(c, P).endpoints
        ]

    c = Cluster.from_dict(FIXTURES["n10_m23_prestress"])
    asked = []
    monkeypatch.setattr(
        expand, "ranks_after_breaking", lambda *a: asked.append(a) or dimension.ranks_after_breaking(*a)
    )
    batched = attempts(c)
    assert asked
    monkeypatch.setattr(expand, "ranks_after_breaking", lambda *a: None)
    assert attempts(c) == batched
