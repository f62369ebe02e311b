"""The network of clusters and paths of each n in a catalogue: its size, components, diameter and circles.

For each ``--n`` of ``--db URL`` (:meth:`packings.service.api.Catalogue.network`): the clusters, the
edges between two clusters, the self-loops, the paths (every broken subset and direction) and of them
the circles and the rearrangements (docs/method.md), the connected components of the undirected network,
its diameter (the most steps between two clusters, each edge a step, over the largest component), and
the shortest route along the paths' directions from the run's seed (the polytetrahedral cluster) to
the cluster with the most contacts, with the contacts of each cluster on it.
"""

from __future__ import annotations

import json

import numpy as np


def add_arguments(p) -> None:
    p.add_argument("--db", required=True, metavar="URL", help="a catalogue")
    p.add_argument("--n", type=int, nargs="+", required=True, help="the numbers of spheres")
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def diameter(g) -> int:
    """The most edges on a shortest path between two nodes of the undirected ``g``'s largest component:
    breadth-first from every node (scipy's, in blocks of rows so that memory stays small)."""
    import networkx as nx
    from scipy.sparse.csgraph import shortest_path

    u = g.to_undirected(as_view=True)
    nodes = max(nx.connected_components(u), key=len)
    a = nx.to_scipy_sparse_array(nx.Graph(u.subgraph(nodes)), format="csr")
    a.setdiag(0)
    a.eliminate_zeros()
    best = 0
    for start in range(0, a.shape[0], 512):
        d = shortest_path(a, unweighted=True, directed=False, indices=np.arange(start, min(start + 512, a.shape[0])))
        best = max(best, int(d[np.isfinite(d)].max()))
    return best


def report(url: str, n: int) -> dict:
    import networkx as nx

    import packings
    from packings.service.network import summary

    with packings.connect(url) as cat:
        g = cat.network(n)
    out = {"n": n, **summary(g), "diameter": diameter(g)}
    seeds = [i for i, d in g.nodes(data=True) if d.get("found_by") == "seed"]
    most = max(d["contacts"] for _, d in g.nodes(data=True))
    top = min(i for i, d in g.nodes(data=True) if d["contacts"] == most)
    route = None
    if seeds:
        try:
            route = nx.shortest_path(g, seeds[0], top)
        except nx.NetworkXNoPath:
            route = None
    out["route"] = None if route is None else [{"id": i, "contacts": g.nodes[i]["contacts"]} for i in route]
    return out


def run(args) -> int:
    rows = [report(args.db, n) for n in args.n]
    if args.json:
        print(json.dumps(rows))
        return 0
    head = "| n | clusters | edges | self-loops | paths | circular | rearranged | components | diameter | seed → most contacts |"
    print(head)
    print("|" + "|".join("---" for _ in range(10)) + "|")
    for r in rows:
        route = "none" if r["route"] is None else " → ".join(str(x["contacts"]) for x in r["route"])
        print(
            f"| {r['n']} | {r['clusters']:,} | {r['edges']:,} | {r['self_loops']:,} | {r['paths']:,} | {r['circular']} "
            f"| {r['rearranged']:,} | {r['components']} | {r['diameter']} | {route} |"
        )
    return 0
