"""The in-memory enumeration reproduces the paper's counts (tests/data/paper_counts.json)."""

import pytest

from packings.workers.params import Params
from tests.helpers import catalogue


def _expected(paper_counts, n):
    return {int(k): v for k, v in paper_counts["clusters_by_contacts"][str(n)].items()}


@pytest.mark.parametrize("n", [5, 6, 7, 8, 9])
def test_counts_match_paper(n, paper_counts):
    cat = catalogue(n)
    assert cat.by_contacts() == _expected(paper_counts, n)
    assert cat.total == paper_counts["totals"][str(n)]
    diag = cat.diagnostics()
    assert diag["expansions"] == cat.total
    assert diag["paths_followed"] > 0


@pytest.mark.slow
def test_counts_n10_match_paper(paper_counts):
    cat = catalogue(10)
    assert cat.by_contacts() == _expected(paper_counts, 10)
    # the hypostatic cluster is singular: one of the clusters reached through a singular cluster's pair breaks
    from packings.workers.rigidity import rigidity

    (hypo,) = [c for c in cat.clusters if c.m == 23]
    r = rigidity(hypo.coords, hypo.contacts, Params())
    assert r.rigid and r.singular and r.flexes == 2 and r.stresses == 1


def test_every_cluster_is_rigid_and_valid():
    from packings.workers.rigidity import rigidity

    cat = catalogue(7)
    for c in cat.clusters:
        assert rigidity(c.coords, c.contacts, Params()).rigid
        assert c.min_distance() > 1 - 1e-5
        assert max(c.m for c in cat.clusters) <= 15
