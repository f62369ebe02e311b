"""Tests of packings.workers.audit (near pairs, adding them as contacts) and packings.workers.identity.geometry_distance."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from packings.workers import kernels
from packings.workers.audit import (
    DOES_NOT_PROJECT,
    NOT_RIGID,
    OVERLAP,
    RIGID,
    near_pairs,
    what_adding_gives,
    with_contacts_added,
)
from packings.workers.cluster import Cluster
from packings.workers.identity import certificate, geometry_distance, same_geometry
from packings.workers.params import DEFAULT
from tests.helpers import (
    CLUSTERS,
    SETTINGS,
    chain,
    names,
    near_misses,
    octahedron,
    seeds,
    tetrahedron_coords,
    transformed,
    two_geometries,
)


def about_axis(p: np.ndarray, a: np.ndarray, b: np.ndarray, degrees: float) -> np.ndarray:
    """``p`` rotated by ``degrees`` about the axis through a and b (Rodrigues)."""
    k = (b - a) / np.linalg.norm(b - a)
    v, t = p - a, np.radians(degrees)
    return a + v * np.cos(t) + np.cross(k, v) * np.sin(t) + k * (k @ v) * (1 - np.cos(t))


def hinged(*degrees: float) -> Cluster:
    """A tetrahedron 0-3 and one sphere per angle, each touching 0 and 1: sphere 3 turned by that angle
    about the axis 0-1 (-70.53 degrees is where sphere 2 is)."""
    x = tetrahedron_coords()
    return Cluster.from_coords(np.vstack([x] + [about_axis(x[3], x[0], x[1], d) for d in degrees]))


# --------------------------------------------------------------------------- geometry_distance


@SETTINGS
@given(names, seeds, st.booleans())
def test_geometry_distance_is_zero_under_rigid_motion_relabelling_and_reflection(name, seed, reflect) -> None:
    c = CLUSTERS[name]
    assert geometry_distance(c, c) < 1e-12
    t = transformed(c, seed, reflect)
    assert geometry_distance(c, t) < 1e-12 and geometry_distance(t, c) < 1e-12


@SETTINGS
@given(names, seeds, st.booleans(), st.floats(0.0, 4.0))
def test_geometry_distance_is_what_same_geometry_compares(name, seed, reflect, scale) -> None:
    """Copies moved by up to a few tol_d: same_geometry holds exactly when the distance is within tol_d."""
    c = CLUSTERS[name]
    moved = transformed(c, seed, reflect, noise=scale * DEFAULT.tol_d)
    d = geometry_distance(c, moved)
    if abs(d - DEFAULT.tol_d) > 1e-12:  # not on the boundary, where rounding decides
        assert same_geometry(c, moved, DEFAULT.tol_d) == (d <= DEFAULT.tol_d)
    assert d <= 2 * scale * DEFAULT.tol_d + 1e-12  # no larger than the noise moved (both centred: twice)


@pytest.mark.parametrize("name", ["glued8", "glued10", "polytetrahedron"])
def test_geometry_distance_measures_a_moved_sphere(name) -> None:
    """One sphere moved by 1e-4: the distance is of that order (the alignment spreads at most part of it)."""
    c = CLUSTERS[name]
    x = c.coords.copy()
    x[0] += [1e-4, 0.0, 0.0]
    d = geometry_distance(c, transformed(Cluster(x, c.contacts), 7, True))
    assert 1e-5 < d <= 1e-4 + 1e-12


def test_the_two_n11_geometries_of_one_graph_are_far_apart() -> None:
    a, b = two_geometries()
    assert certificate(a) == certificate(b)
    assert geometry_distance(a, b) > 0.1 and geometry_distance(b, a) > 0.1  # (a onto b, b onto a: not equal)
    assert geometry_distance(chain(60.0), chain(120.0)) > 0.1


def test_geometry_distance_needs_one_contact_graph() -> None:
    with pytest.raises(ValueError, match="same contact graph"):
        geometry_distance(CLUSTERS["octahedron"], CLUSTERS["polytetrahedron"])


# --------------------------------------------------------------------------- near_pairs


def test_near_pairs_of_the_n12_near_misses() -> None:
    """Each stored near miss has exactly two pairs 2e-4 to 2.5e-4 from touching, both with sphere 7."""
    expected = [((4, 7), (6, 7)), ((0, 7), (5, 7))]
    for m, pairs in zip(near_misses(), expected):
        c = m["cluster"]
        near = near_pairs(c, DEFAULT.tol_a0)
        assert tuple(p.pair for p in near) == pairs
        assert [p.gap for p in near] == sorted(p.gap for p in near)
        for p in near:
            assert 2e-4 < p.gap < 2.5e-4
            assert p.gap == pytest.approx(np.linalg.norm(c.coords[p.i] - c.coords[p.j]) - 1.0, abs=1e-15)
            assert p.pair not in c.contacts
        assert near_pairs(c, 2e-4) == ()  # a smaller tol_a0 excludes them


def test_near_pairs_sorted_by_gap_and_none_in_clean_clusters() -> None:
    o = octahedron()  # its three opposite pairs are sqrt 2 apart
    near = near_pairs(o, 0.5)
    assert sorted(p.pair for p in near) == [(0, 3), (1, 4), (2, 5)]
    assert all(p.gap == pytest.approx(np.sqrt(2.0) - 1.0) for p in near)
    assert near_pairs(o, 0.4) == ()
    c = hinged(-165.0)  # sphere 4, 0.27 from touching sphere 2 and 0.72 from touching sphere 3
    assert [p.pair for p in near_pairs(c, 1.0)] == [(2, 4), (3, 4)]
    assert [p.pair for p in near_pairs(c, 0.5)] == [(2, 4)]
    for name, c in CLUSTERS.items():  # built without pairs within 1e-3 of touching
        assert near_pairs(c, DEFAULT.tol_a0) == (), name


# --------------------------------------------------------------------------- with_contacts_added


def test_adding_the_near_pairs_of_a_near_miss_gives_the_cluster_it_passed_by() -> None:
    """Each near pair alone, and both, close both pairs: the 33-contact cluster, the same for the two
    near misses, every contact exact, the spheres moved by about the gap."""
    found = []
    for m in near_misses():
        c = m["cluster"]
        near = near_pairs(c, DEFAULT.tol_a0)
        results = what_adding_gives(c, near, DEFAULT)
        assert [r.pairs for r in results] == [(near[0].pair,), (near[1].pair,), (near[0].pair, near[1].pair)]
        for r in results:
            assert r.status == RIGID and r.rigidity.rigid
            new = r.cluster
            assert new.m == 33 and set(c.contacts) | {p.pair for p in near} == set(new.contacts)
            f = kernels.residual(new.coords.ravel(), new.edges())
            assert float(f @ f) < DEFAULT.tol
            assert 1e-4 < r.moved < 3e-4
            assert near_pairs(new, DEFAULT.tol_a0) == ()
            found.append(new)
    assert all(same_geometry(found[0], other, DEFAULT.tol_d) for other in found[1:])
    assert not same_geometry(near_misses()[0]["cluster"], near_misses()[1]["cluster"], DEFAULT.tol_d)


def test_adding_nothing_to_a_floppy_cluster_is_not_rigid() -> None:
    c = hinged(-200.0)  # sphere 4 touches 0 and 1 only: it turns about their axis
    r = with_contacts_added(c, [], DEFAULT)
    assert r.status == NOT_RIGID and r.rigidity.flexes == 1 and r.moved < 1e-12
    r = with_contacts_added(c, [(2, 4)], DEFAULT)  # glued onto the face 0-1-2
    assert r.status == RIGID and r.cluster.m == c.m + 1 and r.moved > 0.1


def test_adding_a_pair_that_cannot_touch_does_not_project() -> None:
    """Opposite spheres of the (first-order rigid) octahedron cannot be brought into contact."""
    r = with_contacts_added(octahedron(), [(0, 3)], DEFAULT)
    assert r.status == DOES_NOT_PROJECT and r.cluster is None and r.moved is None


def test_adding_a_pair_that_puts_a_sphere_onto_another_is_an_overlap() -> None:
    """Sphere 4 glued on face 0-1-2 opposite sphere 3; sphere 5 hinged on 0-1 is brought to touch 2:
    the nearest such place is sphere 4's."""
    c = hinged(-141.0576, -250.0)
    assert c.min_distance() > 1 - 1e-12 and (2, 4) in c.contacts and (2, 5) not in c.contacts
    r = with_contacts_added(c, [(2, 5)], DEFAULT)
    assert r.status == OVERLAP and r.cluster.min_distance() < 1e-6 and r.rigidity is None


def test_what_adding_gives_tries_each_pair_then_all() -> None:
    c = hinged(-165.0)
    near = near_pairs(c, 1.0)
    results = what_adding_gives(c, near, DEFAULT)
    assert [r.pairs for r in results] == [((2, 4),), ((3, 4),), ((2, 4), (3, 4))]
    one = what_adding_gives(c, near[:1], DEFAULT)
    assert [r.pairs for r in one] == [((2, 4),)]
    assert what_adding_gives(c, (), DEFAULT) == ()
