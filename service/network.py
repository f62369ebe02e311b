"""The network of clusters and paths of one n: ``packings export network N``, :meth:`Catalogue.network`.

A node per stored cluster of n, with its facts (:func:`packings.service.export.facts`, missing values
left out); a directed edge from each cluster to each cluster its paths reached, with

* ``paths``: how many attempts (broken subset and direction) ended at that cluster, counted as the paper
  counts paths (those taken by symmetry or retraced from their end included); a path that reached no
  stored cluster (floppy, too long, ...) is in no edge,
* ``steps``: the fewest steps of one of them,
* ``broken``: the broken subsets, as JSON ``[[[i, j], ...], ...]`` in the source's labels, distinct and sorted,
* ``circular`` and ``rearranged`` on a self-loop: of its paths, how many came back to every sphere's
  place (the paper's circles) and how many to another isomer of the cluster (docs/method.md).

GraphML and networkx's node-link JSON hold it (:func:`write`); both read back with networkx.
"""

from __future__ import annotations

import json
import os
from collections import defaultdict
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session

from packings.service.errors import NotFound, UsageError
from packings.service.models import ClusterRow
from packings.service.queries import transitions
from packings.workers.outcomes import CIRCULAR, REARRANGED

FORMATS = ("graphml", "json")  #: by the file name's suffix


def network(s: Session, n: int):
    """The network of the stored clusters of n (a ``networkx.DiGraph``; module docstring)."""
    import networkx as nx

    from packings.service.export import facts

    g = nx.DiGraph(n=n)
    for row in s.execute(select(ClusterRow).where(ClusterRow.n == n).order_by(ClusterRow.id)).scalars():
        g.add_node(row.id, **{k: v for k, v in facts(row).items() if v is not None and k != "id"})
    if not g:
        raise NotFound(f"no clusters with n = {n} in the database")
    edges: dict[tuple[int, int], dict] = defaultdict(lambda: {"paths": 0, "steps": None, "broken": set()})
    for t in transitions(s, n=n):
        if t.direction == 0 or t.target_id is None:
            continue
        e = edges[(t.source_id, t.target_id)]
        e["paths"] += 1
        e["steps"] = t.steps if e["steps"] is None else min(e["steps"], t.steps)
        e["broken"].add(t.broken)
        if t.outcome in (CIRCULAR, REARRANGED):
            e[t.outcome] = e.get(t.outcome, 0) + 1
    for (source, target), e in sorted(edges.items()):
        broken = json.dumps(sorted([list(p) for p in b] for b in e.pop("broken")))
        if source == target:
            e = {CIRCULAR: 0, REARRANGED: 0, **e}
        g.add_edge(source, target, broken=broken, **e)
    return g


def format_for(path: str | os.PathLike | None) -> str:
    """The network's format by the file name's suffix (no name: JSON on standard output)."""
    if path is None:
        return "json"
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in FORMATS:
        raise UsageError(f"{path}: a network is written as .graphml or .json, not {suffix or 'no suffix'}")
    return suffix


def text(g, fmt: str) -> str:
    """The network as GraphML or node-link JSON text."""
    import networkx as nx

    if fmt == "graphml":
        return "\n".join(nx.generate_graphml(g)) + "\n"
    return json.dumps(nx.node_link_data(g, edges="edges")) + "\n"


def summary(g) -> dict:
    """What the network is made of: clusters, edges between two clusters, self-loops, paths, circles and
    rearrangements, and the connected components of the undirected network."""
    import networkx as nx

    loops = [d for a, b, d in g.edges(data=True) if a == b]
    return {
        "clusters": g.number_of_nodes(),
        "edges": g.number_of_edges() - len(loops),
        "self_loops": len(loops),
        "paths": sum(d["paths"] for _, _, d in g.edges(data=True)),
        "circular": sum(d[CIRCULAR] for d in loops),
        "rearranged": sum(d[REARRANGED] for d in loops),
        "components": nx.number_connected_components(g.to_undirected(as_view=True)),
    }
