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


@pytest.mark.parametrize(
    "n, contacts, lattices",
    [
        (11, 28, {"fcc", "hcp", "both", "random"}),
        (13, 36, {"fcc", "hcp"}),
        (16, 48, {"fcc", "hcp", "random"}),
        (19, 60, {"fcc", "hcp", "random"}),
    ],
)
def test_a_run_restricted_to_many_contacts_starts_from_a_close_packed_fragment(n, contacts, lattices):
    """Above 3n - 6 contacts the seed is the close-packed fragment with the most contacts the beam search
    finds: for n = 13 ... 19 the paper's maximum M(n) (for n = 10 - 12 one less), rigid, without overlap,
    every contact at distance 1, on a lattice."""
    from packings.workers.classify import lattice_type

    c = seed_cluster(n, Params(min_contacts=3 * n - 5))
    assert c.n == n and c.m == contacts and lattice_type(c.coords, c.contacts) in lattices
    assert c.m == _max_contacts(n) or n <= 12
    d = pair_distances(c.coords)[np.triu_indices(n, 1)]
    assert d.min() > 1 - 1e-12 and sum(abs(d - 1) < 1e-9) == c.m
    assert rigidity(c.coords, c.contacts, Params()).rigid
    assert seed_cluster(n, Params(min_contacts=3 * n - 6)).m == 3 * n - 6  # not above 3n - 6: the polytetrahedron


@pytest.mark.parametrize("n, lattices", [(10, {"both"}), (11, {"hcp"}), (12, {"hcp"})])
def test_a_run_restricted_to_the_maximum_the_beam_misses_starts_from_the_listed_fragment(n, lattices):
    """The maxima M(n) of n = 10, 11, 12 are close-packed fragments the beam search does not keep: the
    seed is then the listing's (every close-packed fragment with at least M(n) contacts)."""
    from packings.workers.classify import lattice_type
    from packings.workers.seeds import close_packed_seed

    m = _max_contacts(n)
    assert close_packed_seed(n).m == m - 1
    c = seed_cluster(n, Params(min_contacts=m))
    assert c.n == n and c.m == m and lattice_type(c.coords, c.contacts) in lattices
    d = pair_distances(c.coords)[np.triu_indices(n, 1)]
    assert d.min() > 1 - 1e-12 and sum(abs(d - 1) < 1e-9) == m
    assert rigidity(c.coords, c.contacts, Params()).rigid


@pytest.mark.parametrize("n, m", [(10, 26), (13, 37)])
def test_no_seed_with_more_contacts_than_any_close_packed_fragment_is_refused_clearly(n, m):
    with pytest.raises(
        ValueError,
        match=f"no cluster of {n} spheres with at least {m} contacts to start from: "
        "no rigid close-packed fragment has that many",
    ):
        seed_cluster(n, Params(min_contacts=m))


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
