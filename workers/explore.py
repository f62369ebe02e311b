"""In-memory enumeration: a small loop over :func:`packings.workers.expand.expand`.

This is the reference loop the service distributes; it keeps everything in
memory and is meant for small n, tests, and checking the service against.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

from packings.workers.cluster import Cluster
from packings.workers.expand import Expansion, expand
from packings.workers.identity import ClusterIndex
from packings.workers.params import Params
from packings.workers.paths import RIGID
from packings.workers.seeds import seed_cluster


@dataclass
class Catalogue:
    """Every rigid cluster found, and the diagnostics of the run."""

    n: int
    params: Params
    clusters: ClusterIndex
    outcomes: Counter = field(default_factory=Counter)
    expansions: int = 0
    paths_followed: int = 0
    widened_paths: int = 0
    paths_by_symmetry: int = 0  #: paths not followed, their endpoints the images of paths followed (expand)
    seconds: float = 0.0

    def by_contacts(self) -> dict[int, int]:
        """Number of clusters by number of contacts."""
        return dict(sorted(Counter(c.m for c in self.clusters).items()))

    @property
    def total(self) -> int:
        return len(self.clusters)

    def diagnostics(self) -> dict:
        """Counts a disagreement with the paper can be investigated with."""
        return {
            "expansions": self.expansions,
            "paths_followed": self.paths_followed,
            "paths_by_symmetry": self.paths_by_symmetry,
            "widened_paths": self.widened_paths,
            **{k: v for k, v in sorted(self.outcomes.items())},
            "seconds": round(self.seconds, 2),
        }


def explore(
    n: int,
    params: Params | None = None,
    seeds: list[Cluster] | None = None,
    on_expansion: Callable[[int, Expansion, Catalogue], None] | None = None,
) -> Catalogue:
    """Expand every cluster reachable from the seeds by one-dimensional paths."""
    params = params or Params()
    start = time.perf_counter()
    index = ClusterIndex()
    cat = Catalogue(n, params, index)
    for s in seeds or [seed_cluster(n, params)]:
        index.add(s, params.tol_d)
    done = 0
    while done < len(index):
        ex = expand(index[done], params)
        cat.outcomes.update(ex.outcomes())
        cat.paths_followed += ex.paths_followed
        cat.widened_paths += ex.widened_paths
        cat.paths_by_symmetry += ex.paths_by_symmetry
        for e in ex.endpoints:
            if e.outcome == RIGID:
                index.add(e.cluster, params.tol_d)
        done += 1
        cat.expansions = done
        if on_expansion is not None:
            on_expansion(done, ex, cat)
    cat.seconds = time.perf_counter() - start
    return cat
