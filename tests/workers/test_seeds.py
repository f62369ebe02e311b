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
