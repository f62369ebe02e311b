"""Tests of packings.workers.free_energy: the sticky-limit geometric factor z of Z = κ^m z."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from benchmarks.free_energy import distance_symmetries, reduced_integral
from packings.workers.cluster import Cluster
from packings.workers.explore import explore
from packings.workers.free_energy import (
    HYPERSTATIC,
    HYPOSTATIC,
    REGULAR,
    SINGULAR,
    equilibrium_shares,
    free_energy,
    log_frame_constant,
    shares,
    square_well_moment,
    symmetry_numbers,
)
from tests.helpers import chain, congruent_copy, glue_away, tetrahedron, tetrahedron_coords, transformed

DATA = Path(__file__).resolve().parents[1] / "data"
SETTINGS = settings(derandomize=True, max_examples=20, deadline=None, database=None)


def trigonal_bipyramid() -> Cluster:
    x = tetrahedron_coords()
    return Cluster.from_coords(np.vstack([x, glue_away(x, (0, 1, 2), 3)]))


def octahedron() -> Cluster:
    h = 1.0 / math.sqrt(2.0)
    return Cluster.from_coords(np.array([[h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0], [0, 0, h], [0, 0, -h]]))


def polytetrahedron() -> Cluster:
    """Three tetrahedra joined face to face in a row (the other rigid cluster of six)."""
    x = tetrahedron_coords()
    x = np.vstack([x, glue_away(x, (0, 1, 2), 3)])
    return Cluster.from_coords(np.vstack([x, glue_away(x, (0, 1, 4), 2)]))


@pytest.fixture(scope="module")
def clusters() -> dict[int, list[Cluster]]:
    """Every rigid cluster of n = 4, ..., 7 (1, 1, 2, 5 of them)."""
    return {n: list(explore(n).clusters) for n in (4, 5, 6, 7)}


def test_the_symmetry_numbers_of_known_shapes():
    """σ counts the proper rotations: T (12) of the tetrahedron, D3 (6) of the trigonal bipyramid, O (24) of
    the octahedron, C2 (2) of the polytetrahedron; each of them also has as many improper symmetries."""
    for cluster, sigma in [(tetrahedron(), 12), (trigonal_bipyramid(), 6), (octahedron(), 24), (polytetrahedron(), 2)]:
        assert symmetry_numbers(cluster) == (sigma, 2 * sigma)
        fe = free_energy(cluster)
        assert fe.kind == REGULAR and fe.sigma == sigma and not fe.chiral


@settings(SETTINGS, max_examples=40)
@given(st.sampled_from([0.0, 180.0]), st.integers(0, 2**31 - 1), st.booleans())
def test_a_planar_cluster_has_a_proper_and_an_improper_map_for_each_symmetry(dihedral, seed, reflect):
    """A cluster in a plane is its own mirror image: each of its symmetries is a proper rotation and an
    improper map, wherever it is moved, reflected or relabelled (the alignment alone gave either, as
    rounding fell, and a proper count of 0). The equilateral triangle: σ = 6 (D3h's rotations), not chiral;
    the flat 4-chains (trans and cis): σ = 2."""
    c = transformed(chain(dihedral), seed, reflect)
    assert symmetry_numbers(c) == (2, 4)
    triangle = transformed(Cluster(tetrahedron_coords()[:3], ((0, 1), (0, 2), (1, 2))), seed, reflect)
    assert symmetry_numbers(triangle) == (6, 12)
    fe = free_energy(triangle)
    assert fe.sigma == 6 and not fe.chiral


def test_the_tetrahedron_worked_by_hand():
    """Unit tetrahedron: I = 1 (each centre sqrt(3/8) from the middle: 4 (3/8)(2/3) = 1 on every axis);
    R Rᵀ = 2 + A/2 with A the adjacency of the octahedral line graph of K4 (eigenvalues 4, 0 x3, -2 x2), so
    its eigenvalues are 4, 2 x3, 1 x2 and ∏ λ = sqrt(32); σ = 12: z = 1 / (12 sqrt(32))."""
    fe = free_energy(tetrahedron())
    assert fe.log_rotational == pytest.approx(0.0, abs=1e-12)
    assert fe.log_vibrational == pytest.approx(-0.5 * math.log(32.0), abs=1e-12)
    assert fe.z == pytest.approx(1.0 / (12.0 * math.sqrt(32.0)), rel=1e-12)
    assert fe.log_z == pytest.approx(math.log(fe.z), abs=1e-12)


def test_the_rigid_clusters_of_six_and_seven(clusters):
    """explore(6) finds the octahedron (σ 24) and the polytetrahedron (σ 2); of the five of seven one is
    chiral (its z counts both mirror images) and one is the pentagonal bipyramid (D5, σ 10)."""
    assert sorted(free_energy(c).sigma for c in clusters[6]) == [2, 24]
    seven = [free_energy(c) for c in clusters[7]]
    assert all(fe.kind == REGULAR for fe in seven)
    assert sorted(fe.sigma for fe in seven) == [2, 2, 3, 3, 10]
    assert [fe.sigma for fe in seven if fe.chiral] == [2]


@SETTINGS
@given(seed=st.integers(0, 2**32 - 1), reflect=st.booleans(), which=st.integers(0, 8))
def test_z_is_invariant_under_rotation_reflection_translation_and_relabelling(clusters, seed, reflect, which):
    every = [c for n in (4, 5, 6, 7) for c in clusters[n]]
    cluster = every[which]
    copy, _ = congruent_copy(cluster, seed, reflect)
    a, b = free_energy(cluster), free_energy(copy)
    assert (b.sigma, b.chiral, b.kind) == (a.sigma, a.chiral, a.kind)
    assert b.log_z == pytest.approx(a.log_z, abs=1e-9)
    assert b.log_vibrational == pytest.approx(a.log_vibrational, abs=1e-9)
    assert b.log_rotational == pytest.approx(a.log_rotational, abs=1e-9)


def test_octahedron_against_polytetrahedron_as_published(clusters):
    """Meng, Arkus, Brenner & Manoharan (Science 2010): in equilibrium the octahedron is about 4 % of the
    clusters of six, the polytetrahedron about 96 %, observed "more than twenty times as often".  The geometric
    factors are in the ratio 24 : 1, 12 from the symmetry numbers (24 against 2) and 2 from the vibrational and
    rotational parts together."""
    oct_, poly = free_energy(octahedron()), free_energy(polytetrahedron())
    assert poly.z / oct_.z == pytest.approx(24.0, rel=1e-9)
    parts = math.exp(poly.log_vibrational + poly.log_rotational - oct_.log_vibrational - oct_.log_rotational)
    assert parts == pytest.approx(2.0, rel=1e-9)
    energies = [free_energy(c) for c in clusters[6]]
    shares = equilibrium_shares(energies, [c.m for c in clusters[6]], log_kappa=1.7)
    octahedral = shares[[fe.sigma for fe in energies].index(24)]
    assert octahedral == pytest.approx(0.04, abs=1e-9)


def fixture(name: str) -> Cluster:
    return Cluster.from_dict(json.loads((DATA / "clusters_n10.json").read_text())[name])


def test_no_z_where_the_formula_does_not_apply_but_the_square_well_term(clusters):
    """Singular (n = 9's one, and one of n = 10), hypostatic and hyperstatic clusters get no z but a reason, and
    a share of the clusters of n that would leave them out is not given; with one self-stress and a flexes
    they get the leading term κ^m ε^(a/2 - 1) z_sw of a square well; a regular one gets z = z_sw, power 0."""
    singular = [fe for fe in map(free_energy, explore(9).clusters) if fe.kind != REGULAR]
    assert [fe.kind for fe in singular] == [SINGULAR]
    cases = [
        (singular[0], SINGULAR, 1, 1),
        (free_energy(fixture("n10_m24_prestress")), SINGULAR, 1, 1),
        (free_energy(fixture("n10_m23_prestress")), HYPOSTATIC, 2, 1),
        (free_energy(fixture("n10_m25_first-order")), HYPERSTATIC, 0, 1),
    ]
    for fe, kind, a, b in cases:
        assert fe.kind == kind and fe.z is None and fe.log_z is None
        assert fe.reason.startswith(kind) and "Kallus & Holmes-Cerfon 2017" in fe.reason
        assert (fe.flexes, fe.stresses) == (a, b) and fe.eps_power == a / 2 - 1 and fe.square_well > 0
        assert fe.sigma >= 1 and math.isfinite(fe.log_rotational)
    regular = free_energy(fixture("n10_m24_first-order"))
    assert regular.kind == REGULAR and regular.z > 0 and regular.reason is None
    assert (regular.flexes, regular.stresses, regular.eps_power, regular.square_well) == (0, 0, 0.0, regular.z)
    assert equilibrium_shares([regular, cases[0][0]], [24, 24]) is None


def test_the_square_well_moments_worked_by_hand():
    """w = (1, -1)/sqrt 2: wᵀσ has the triangular density sqrt 2 (1 - sqrt 2 |h|) on |h| <= 1/sqrt 2, so its
    density at 0 is sqrt 2, P(h > 0) = 1/2 and E[h_+^(-1/2)] = (4/3) 2^(1/4)."""
    w = np.array([1.0, -1.0]) / math.sqrt(2.0)
    assert square_well_moment(w, 0) == pytest.approx(math.sqrt(2.0), rel=3e-4)  # a kink at 0: first order in the step
    assert square_well_moment(w, 1) == pytest.approx(4.0 / 3.0 * 2.0**0.25, rel=1e-6)
    assert square_well_moment(w, 2) == pytest.approx(0.5, abs=1e-9)


def test_the_formula_against_a_monte_carlo_integration_of_a_square_well(clusters):
    """The configuration integral of each basin of n = 4, 5, 6 under a square well of width ε = 1e-4, by a
    seeded Monte Carlo integration that uses none of the formulas (benchmarks/free_energy.py), divided by
    ε^m, is 8π² n^{3/2} z within its statistical error and the O(ε) of a finite well; its count of the
    copies of each cluster (permutations preserving every distance, by exhaustive search) is twice σ."""
    rng = np.random.default_rng(2026)
    eps = 1e-4
    for n in (4, 5, 6):
        for cluster in clusters[n]:
            fe = free_energy(cluster)
            assert distance_symmetries(cluster) == 2 * fe.sigma
            q, err, est = reduced_integral(cluster, eps, 40_000, rng)
            assert est["edge"] < 0.9  # no sample in the basin near the edge of a sampling window
            predicted = math.exp(log_frame_constant(n) + fe.log_z)
            assert abs(q / predicted - 1.0) <= 4.0 * err / predicted + 3.0 * eps


def test_the_square_well_terms_against_the_monte_carlo_integration():
    """The same integration for n = 9's singular cluster (one flex: Q grows as ε^(m - 1/2), its non-contact
    coordinates drawn within 3 sqrt(ε)), a hypostatic cluster of 10 (two flexes, one stress: ε^m; one of its
    spheres lies in the plane of the three it touches and crosses it within the basin) and a hyperstatic one
    with one extra contact (ε^(m - 1))."""
    rng = np.random.default_rng(72)
    eps = 1e-4
    singular = next(c for c in explore(9).clusters if free_energy(c).kind == SINGULAR)
    for cluster in (singular, fixture("n10_m23_prestress"), fixture("n10_m25_first-order")):
        fe = free_energy(cluster)
        q, err, est = reduced_integral(cluster, eps, 40_000, rng, fe.eps_power, fe.flexes)
        assert est["edge"] < 0.9
        predicted = math.exp(log_frame_constant(cluster.n)) * fe.square_well
        assert abs(q / predicted - 1.0) <= 4.0 * err / predicted + 10.0 * math.sqrt(eps)


@SETTINGS
@given(
    log_z=st.lists(st.floats(-30.0, 30.0), min_size=2, max_size=8),
    data=st.data(),
    log_kappa=st.floats(-5.0, 9.0),
    factor=st.floats(-3.0, 3.0),
)
def test_shares_sum_to_one_and_scale_as_kappa_to_the_contacts(log_z, data, log_kappa, factor):
    """Shares are probabilities, unchanged by relabelling the clusters, and multiplying κ by e^f multiplies
    the odds of cluster a against b by e^(f (m_a - m_b)): κ^m is the only place κ enters."""
    k = len(log_z)
    contacts = np.array(data.draw(st.lists(st.integers(30, 40), min_size=k, max_size=k)))
    log_z = np.array(log_z)
    p = shares(log_z, contacts, log_kappa)
    assert p.sum() == pytest.approx(1.0) and (p >= 0).all()
    perm = np.array(data.draw(st.permutations(range(k))))
    assert shares(log_z[perm], contacts[perm], log_kappa) == pytest.approx(p[perm], abs=1e-12)
    q = shares(log_z, contacts, log_kappa + factor)
    if p[0] > 1e-200 and p[1] > 1e-200 and q[0] > 1e-200 and q[1] > 1e-200:
        odds = math.log(q[0] / q[1]) - math.log(p[0] / p[1])
        assert odds == pytest.approx(factor * (contacts[0] - contacts[1]), abs=1e-6)
    both = shares(log_z, contacts, np.array([log_kappa, log_kappa + factor]))
    assert both == pytest.approx(np.vstack([p, q]), abs=1e-12)


def test_the_square_well_moment_of_a_stress_with_entries_of_every_size():
    """n = 11's singular cluster whose self-stress has entries from 0.28 down to rounding (one flex): J_1 is
    E[(wᵀσ)_+^(-1/2)], about 1.60 by a seeded Monte Carlo estimate; building the distribution term by term
    must not divide the grid's rounding by the tiny entries (it once gave a negative J and a failed write-back)."""
    from packings.workers.free_energy import flexes_and_stresses

    cluster = Cluster.from_dict(json.loads((DATA / "n11_stress_widths.json").read_text())["n11_singular_stress_widths"])
    _, flexes, stresses = flexes_and_stresses(cluster.coords, cluster.contacts, 1e-8)
    w = stresses[:, 0]
    assert flexes.shape[1] == 1 and np.abs(w).min() < 1e-6 < 0.2 < np.abs(w).max()
    h = np.random.default_rng(0).random((400_000, w.size)) @ w
    for sign in (1.0, -1.0):
        mc = np.mean(np.where(sign * h > 0, np.abs(h) ** -0.5, 0.0))
        assert square_well_moment(sign * w, 1) == pytest.approx(mc, rel=0.02)
        assert square_well_moment(sign * w, 2) == pytest.approx(np.mean(sign * h > 0), abs=0.005)
    fe = free_energy(cluster)
    assert fe.kind == SINGULAR and fe.eps_power == -0.5 and fe.square_well > 0
