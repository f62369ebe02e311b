"""The rigidity test: first order, floppy, pre-stress stable (single flex and SDP), undecided."""

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packings.workers import kernels
from packings.workers.cluster import Cluster
from packings.workers.dimension import solution_dimension
from packings.workers.params import Params
from packings.workers.rigidity import (
    FIRST_ORDER,
    FLOPPY,
    PRESTRESS,
    UNDECIDED,
    FirstTriangles,
    contact_triangle,
    prestress_test,
    rigidity,
    sdp_margin,
)
from packings.workers.seeds import seed_cluster
from tests.helpers import congruent_copy

P = Params()
FIXTURES = json.loads((Path(__file__).parents[1] / "data" / "clusters_n10.json").read_text())


def fixture(name) -> Cluster:
    return Cluster.from_dict(FIXTURES[name])


def test_first_order_rigid():
    r = rigidity(seed_cluster(9).coords, seed_cluster(9).contacts, P)
    assert r.rigid and r.kind == FIRST_ORDER and r.flexes == 0 and not r.singular


def test_floppy_after_deleting_a_contact():
    c = seed_cluster(9)
    r = rigidity(c.coords, c.contacts[1:], P)
    assert not r.rigid and r.kind == FLOPPY and r.flexes == 1 and r.stresses == 0


def test_chain_is_floppy_with_many_flexes():
    x = np.array(
        [[0, 0, 0], [1, 0, 0], [0.5, np.sqrt(3) / 2, 0], [1.5, np.sqrt(3) / 2, 0.0], [2.5, np.sqrt(3) / 2, 0.0]]
    )
    r = rigidity(x, [(0, 1), (0, 2), (1, 2), (1, 3), (3, 4)], P)
    assert not r.rigid and r.flexes == 9 - 5  # 3n - 6 free coordinates, 5 independent contacts


def test_hyperstatic_regular_cluster_has_a_stress_and_no_flex():
    c = fixture("n10_m25_first-order")
    assert c.m == 25
    r = rigidity(c.coords, c.contacts, P)
    assert r.rigid and r.kind == FIRST_ORDER and r.stresses == 1


@pytest.mark.parametrize(
    "name, contacts, flexes",
    [
        ("n10_m24_prestress", 24, 1),  # isostatic but singular: one flex blocked by one stress
        ("n10_m23_prestress", 23, 2),  # hypostatic (3n - 7 contacts): two flexes, one stress
    ],
)
def test_singular_prestress_stable_clusters(name, contacts, flexes):
    """Singular n = 10 clusters from our own enumeration: rigid only through the stress's second-order form."""
    c = fixture(name)
    assert c.m == contacts
    r = rigidity(c.coords, c.contacts, P)
    assert r.rigid and r.singular and r.kind == PRESTRESS
    assert (r.flexes, r.stresses) == (flexes, 1)
    assert r.margin > 1e-2


def test_singular_cluster_is_not_first_order_rigid_when_stress_ignored():
    c = fixture("n10_m24_prestress")
    tri = contact_triangle(c.contacts)
    x = kernels.to_frame(c.coords, tri).ravel()
    ns = kernels.null_spaces(x, c.edges(), kernels.free_coordinates(c.n, tri), P.tol_n)
    assert ns.V.shape[1] == 1  # a linear flex exists: only the stress makes it rigid
    R = kernels.rigidity_matrix(x, c.edges())
    assert np.allclose(ns.W[:, 0] @ R[:, kernels.free_coordinates(c.n, tri)], 0, atol=1e-8)


def test_hyperstatic_cluster_needs_two_breaks_for_a_path():
    """Deleting one contact of a 25-contact regular cluster whose stress touches it leaves it rigid;
    deleting two leaves a one-dimensional set."""
    c = fixture("n10_m25_first-order")
    e = c.edges()

    def dim(keep):
        tri = contact_triangle(keep)
        x = kernels.to_frame(c.coords, tri).ravel()
        return solution_dimension(x, keep, kernels.free_coordinates(c.n, tri), P).dim

    tri = contact_triangle(e)
    x = kernels.to_frame(c.coords, tri).ravel()
    w = kernels.null_spaces(x, e, kernels.free_coordinates(c.n, tri), P.tol_n).W[:, 0]
    stressed = [k for k in range(c.m) if abs(w[k]) > 1e-6]
    assert stressed
    assert all(dim(np.delete(e, k, 0)) == 0 for k in stressed[:6])
    assert dim(np.delete(e, stressed[:2], 0)) == 1


def test_sdp_finds_a_combination_no_single_stress_gives():
    Q = np.array([np.diag([1.0, -0.5]), np.diag([-0.5, 1.0])])
    rigid, method, margin = prestress_test(Q, P.tol_psd)
    assert rigid and method == "sdp"
    assert margin == pytest.approx(0.5, abs=1e-6)  # c = (1, 1): diag(0.5, 0.5)


def test_without_the_sdp_the_cheap_cases_alone_decide(monkeypatch):
    """``sdp=False``: the pencil only a combination makes definite is left undecided, with the cheap cases'
    best margin, and no SDP is solved; a definite single stress is still found."""
    from packings.workers import rigidity as rg

    monkeypatch.setattr(rg, "sdp_margin", lambda Q: pytest.fail("an SDP was solved"))
    Q = np.array([np.diag([1.0, -0.5]), np.diag([-0.5, 1.0])])
    rigid, method, margin = prestress_test(Q, P.tol_psd, sdp=False)
    assert (rigid, method) == (False, "e_k") and margin == pytest.approx(-0.5)
    rigid, method, margin = prestress_test(np.array([np.diag([1.0, -0.5]), np.diag([2.0, 1.0])]), P.tol_psd, sdp=False)
    assert (rigid, method) == (True, "e_k") and margin == pytest.approx(1.0)


def test_sdp_says_no_when_no_combination_is_definite():
    Q = np.array([np.diag([1.0, -1.0]), np.array([[0.0, 1.0], [1.0, 0.0]])])
    rigid, method, margin = prestress_test(Q, P.tol_psd)
    assert not rigid and method == "sdp"
    assert margin <= 1e-6


@settings(max_examples=20, deadline=None, derandomize=True)
@given(st.integers(2, 4), st.integers(2, 4), st.integers(0, 2**31 - 1))
def test_sdp_margin_lies_between_independent_bounds(a, b, seed):
    """t* = max_c lambda_min(sum c_k Q_k) over |c_k| <= 1.

    Any feasible c (c = 0 included) bounds it from below; any unit vector u bounds
    it from above: t* <= sum_k |u^T Q_k u|.
    """
    rng = np.random.default_rng(seed)
    Q = rng.standard_normal((b, a, a))
    Q = Q + Q.transpose(0, 2, 1)
    t = sdp_margin(Q)
    cs = np.vstack([np.zeros(b), rng.uniform(-1, 1, (3000, b))])
    lower = max(np.linalg.eigvalsh(np.tensordot(c, Q, 1))[0] for c in np.vstack([cs, np.sign(cs)]))
    us = rng.standard_normal((3000, a))
    us /= np.linalg.norm(us, axis=1, keepdims=True)
    upper = np.abs(np.einsum("ui,kij,uj->uk", us, Q, us)).sum(axis=1).min()
    assert lower - 1e-6 <= t <= upper + 1e-6
    assert t >= -1e-6


def test_sdp_margin_of_a_definite_pencil():
    Q = np.array([np.diag([2.0, 1.0, 3.0]), np.diag([1.0, -1.0, 0.0])])
    # c = (1, c2): diag(2 + c2, 1 - c2, 3), best at c2 = -1/2
    assert sdp_margin(Q) == pytest.approx(1.5, abs=1e-6)


def test_undecided_kind_when_stresses_do_not_help():
    Q = np.array([[[0.0]]])
    rigid, method, _ = prestress_test(Q, P.tol_psd)
    assert not rigid and method == "single-flex"
    assert UNDECIDED == "undecided"


def test_hypostatic_cluster_minus_a_contact_is_not_rigid():
    c = fixture("n10_m23_prestress")
    for k in range(0, c.m, 5):
        r = rigidity(c.coords, c.contacts[:k] + c.contacts[k + 1 :], P)
        assert not (r.rigid and r.kind == FIRST_ORDER)
        assert r.flexes >= 2


@settings(max_examples=15, deadline=None, derandomize=True)
@given(st.sampled_from(sorted(FIXTURES)), st.integers(0, 2**31 - 1), st.booleans())
def test_rigidity_invariant_under_rotation_reflection_relabelling(name, seed, reflect):
    c = fixture(name)
    moved = congruent_copy(c, seed, reflect)[0]
    a, b = rigidity(c.coords, c.contacts, P), rigidity(moved.coords, moved.contacts, P)
    assert (a.rigid, a.kind, a.flexes, a.stresses) == (b.rigid, b.kind, b.flexes, b.stresses)
    # the margin's size depends on which triangle is pinned (it scales the flexes); its sign does not
    if a.margin is not None:
        assert (a.margin > P.tol_psd) == (b.margin > P.tol_psd)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.sampled_from(sorted(FIXTURES) + ["seed 9", "chain"]), st.integers(0, 2**31 - 1), st.integers(0, 30))
def test_the_first_triangle_after_deleting_contacts_is_contact_triangles(name, seed, k):
    """FirstTriangles gives, for any contacts deleted, the triangle contact_triangle finds in what is left
    (None where no triangle is left), relabelled clusters and deletions of most contacts included."""
    c = (
        seed_cluster(9)
        if name == "seed 9"
        else Cluster(np.zeros((5, 3)), [(0, 1), (1, 2), (2, 3), (3, 4)])
        if name == "chain"
        else fixture(name)
    )
    rng = np.random.default_rng(seed)
    perm = rng.permutation(c.n)
    c = Cluster(c.coords[np.argsort(perm)], [(perm[i], perm[j]) for i, j in c.contacts])
    edges = c.edges()
    idx = tuple(sorted(rng.choice(c.m, size=min(k, c.m), replace=False).tolist()))
    kept = np.ones(c.m, dtype=bool)
    kept[list(idx)] = False
    assert FirstTriangles(c.contacts).after_deleting(idx) == contact_triangle(edges[kept])
