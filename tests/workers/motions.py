"""Random congruent copies of a cluster, for the tests of invariance under rotation, reflection and relabelling."""

import numpy as np

from packings.workers.cluster import Cluster


def congruent_copy(c: Cluster, rng: np.random.Generator | int, reflect: bool) -> tuple[Cluster, np.ndarray]:
    """``c`` rotated (and reflected if asked), translated and relabelled at random; and ``inv``: sphere i of
    ``c`` is sphere ``inv[i]`` of the copy.  ``rng`` is a generator or a seed for one."""
    rng = np.random.default_rng(rng)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    if reflect:
        q = q @ np.diag([1.0, 1.0, -1.0])
    perm = rng.permutation(c.n)
    inv = np.argsort(perm)
    return Cluster(c.coords[perm] @ q.T + rng.standard_normal(3), [(inv[i], inv[j]) for i, j in c.contacts]), inv
