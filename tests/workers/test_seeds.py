import numpy as np
import pytest

from packings.workers.cluster import pair_distances
from packings.workers.params import Params
from packings.workers.rigidity import rigidity
from packings.workers.seeds import seed_cluster


@pytest.mark.parametrize("n", range(4, 16))
def test_seed_is_rigid_isostatic_without_overlap(n):
    c = seed_cluster(n)
    assert c.n == n
    assert c.m == 3 * n - 6
    d = pair_distances(c.coords)[np.triu_indices(n, 1)]
    assert d.min() > 1 - 1e-12
    for i, j in c.contacts:
        assert abs(np.linalg.norm(c.coords[i] - c.coords[j]) - 1) < 1e-12
    r = rigidity(c.coords, c.contacts, Params())
    assert r.rigid and r.kind == "first-order"


@pytest.mark.parametrize("n", [-1, 0, 3])
def test_seed_rejects_small_n(n):
    with pytest.raises(ValueError):
        seed_cluster(n)


def _max_contacts(n: int) -> int:
    import json
    from pathlib import Path

    return json.loads((Path(__file__).parents[1] / "data" / "paper_counts.json").read_text())["max_contacts"][str(n)]


@pytest.mark.parametrize("n, contacts, lattices", [(11, 28, {"fcc", "hcp", "both", "random"}), (13, 36, {"fcc", "hcp"}),
                                                   (16, 48, {"fcc", "hcp", "random"}), (19, 60, {"fcc", "hcp", "random"})])
def test_a_run_restricted_to_many_contacts_starts_from_a_close_packed_fragment(n, contacts, lattices):
    """Above 3n - 6 contacts the seed is the close-packed fragment with the most contacts found: for
    n = 13 ... 19 the paper's maximum M(n) (n = 10 - 12 have a non-close-packed one, one more), rigid,
    without overlap, every contact at distance 1, on a lattice."""
    from packings.workers.classify import lattice_type

    c = seed_cluster(n, Params(min_contacts=3 * n - 5))
    assert c.n == n and c.m == contacts and lattice_type(c.coords, c.contacts) in lattices
    assert c.m == _max_contacts(n) or n <= 12
    d = pair_distances(c.coords)[np.triu_indices(n, 1)]
    assert d.min() > 1 - 1e-12 and sum(abs(d - 1) < 1e-9) == c.m
    assert rigidity(c.coords, c.contacts, Params()).rigid
    assert seed_cluster(n, Params(min_contacts=3 * n - 6)).m == 3 * n - 6  # not above 3n - 6: the polytetrahedron


def test_no_seed_with_more_contacts_than_found_is_refused_clearly():
    with pytest.raises(ValueError, match="no cluster of 13 spheres with at least 37 contacts to start from: "
                                         "the close-packed fragment with the most contacts found has 36"):
        seed_cluster(13, Params(min_contacts=37))


def test_lattice_sites_are_close_packed():
    from packings.workers.seeds import lattice_sites

    for kind in ("fcc", "hcp"):
        x = lattice_sites(kind, radius=2.5)
        d = pair_distances(x)
        origin = int(np.argmin(np.linalg.norm(x, axis=1)))
        assert np.allclose(x[origin], 0) and np.sum(np.abs(d[origin] - 1) < 1e-9) == 12  # 12 neighbours each
        assert d[np.triu_indices(len(x), 1)].min() > 1 - 1e-9
    with pytest.raises(ValueError, match="unknown lattice"):
        lattice_sites("bcc")
