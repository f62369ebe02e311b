"""The network of clusters and paths: ``Catalogue.network`` and ``packings export network N``."""

from __future__ import annotations

import json
from collections import Counter

import networkx as nx
from sqlalchemy import select

from packings.service.api import Catalogue
from packings.service.db import sessions
from packings.service.models import ClusterRow
from packings.service.queries import transitions
from tests.helpers import filled_catalog, ok, one_line_error, packings

catalog = filled_catalog(6, 8)


def _paths(engine, n: int) -> tuple[list, set[int]]:
    """The stored paths from the clusters of n that reached a cluster, and the ids of those clusters."""
    with sessions(engine)() as s:
        ids = set(s.execute(select(ClusterRow.id).where(ClusterRow.n == n)).scalars())
        rows = [t for t in transitions(s) if t.direction != 0]
        return [t for t in rows if t.source_id in ids and t.target_id is not None], ids


def test_the_network_holds_every_path_between_the_clusters(catalog):
    """A node per cluster of n with its facts; an edge per (start, end) pair with as many paths as the stored
    attempts that went that way, and self-loops that count circles and rearrangements apart."""
    paths, ids = _paths(catalog.engine, 8)
    with Catalogue(catalog.url) as cat:
        g = cat.network(8)
        stats = cat.stats(8)[0]
    assert set(g.nodes) == ids and all(g.nodes[i]["n"] == 8 for i in g)
    per_edge = Counter((t.source_id, t.target_id) for t in paths)
    assert {(a, b): d["paths"] for a, b, d in g.edges(data=True)} == dict(per_edge)
    for a, b, d in g.edges(data=True):
        went = [t for t in paths if (t.source_id, t.target_id) == (a, b)]
        assert d["steps"] == min(t.steps for t in went)
        assert json.loads(d["broken"]) == sorted([list(p) for p in b] for b in {t.broken for t in went})
    loops = [d for a, b, d in g.edges(data=True) if a == b]
    assert sum(d["rearranged"] for d in loops) == stats["rearranged_paths"] > 0
    assert sum(d["circular"] for d in loops) == stats["circular_paths"] == 0
    assert sum(d["paths"] for _, _, d in g.edges(data=True)) <= stats["paths"]  # less those that reached none


def test_export_network_round_trips_through_networkx(catalog, tmp_path):
    with Catalogue(catalog.url) as cat:
        g = cat.network(6)
    graphml, js = tmp_path / "six.graphml", tmp_path / "six.json"
    out = ok("export", "network", "6", "-o", str(graphml), "--db", catalog.url)
    assert out.startswith(f"wrote the network of n = 6 (graphml) to {graphml}: 2 clusters")
    back = nx.read_graphml(graphml, node_type=int)
    assert dict(back.nodes(data=True)) == dict(g.nodes(data=True))
    assert sorted(back.edges(data=True)) == sorted(g.edges(data=True))
    ok("export", "network", "6", "-o", str(js), "--db", catalog.url)
    back = nx.node_link_graph(json.loads(js.read_text()), edges="edges")
    assert dict(back.nodes(data=True)) == dict(g.nodes(data=True))
    assert sorted(back.edges(data=True)) == sorted(g.edges(data=True))
    assert json.loads(ok("export", "network", "6", "--db", catalog.url)) == json.loads(js.read_text())


def test_export_network_errors_are_one_line(catalog, tmp_path):
    r = packings("export", "network", "--db", catalog.url)
    assert r.returncode == 2 and "give N" in one_line_error(r)
    r = packings("export", "network", "12", "--db", catalog.url)
    assert r.returncode == 1 and "no clusters with n = 12" in one_line_error(r)
    one_line_error(packings("export", "network", "6", "-o", str(tmp_path / "six.txt"), "--db", catalog.url), ".graphml")
    assert not (tmp_path / "six.txt").exists()
    r = packings("export", "n=6", "7", "--db", catalog.url)
    assert r.returncode == 2 and "one SELECTION only" in one_line_error(r)
