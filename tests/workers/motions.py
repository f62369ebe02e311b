"""Random congruent copies of a cluster, for the tests of invariance under rotation, reflection and relabelling."""

import numpy as np

from packings.workers.cluster import Cluster
from tests.workers.test_identity import random_orthogonal, relabel


def congruent_copy(c: Cluster, rng: np.random.Generator | int, reflect: bool) -> tuple[Cluster, np.ndarray]:
    """``c`` rotated (reflected too if asked), translated and relabelled at random; and ``inv``: sphere i of
    ``c`` is sphere ``inv[i]`` of the copy.  ``rng`` is a generator or a seed for one."""
    rng = np.random.default_rng(rng)
    q = random_orthogonal(rng, reflect)
    perm = rng.permutation(c.n)
    return relabel(c, perm, c.coords @ q.T + rng.standard_normal(3)), np.argsort(perm)
