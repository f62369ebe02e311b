"""What a catalogue contains, per n, in the paper's style: ``packings stats``.

:func:`stats` reads the facts stored with every cluster (contacts, singular,
lattice, min_gap, certificate) and the paths (attempts and edges), and returns one plain dict
per n; :func:`format_stats` prints them as tables.  Transition counts add up
over every run of that n (normally there is one).
"""

from __future__ import annotations

import math

from sqlalchemy import func, select
from sqlalchemy.orm import Session, aliased

from packings.service.export import counted, table
from packings.service.fit import fit_factorial
from packings.service.models import NOT_CLOSE_PACKED, AttemptsRow, ClusterRow, Edge, ExpansionRow
from packings.service.paper import against_paper, verdict
from packings.service.queries import counts_by_n, incomplete_ns

#: how many of the smallest gaps are listed
SMALLEST = 10


def _by(s: Session, n: int, *where) -> dict[int, int]:
    """Clusters of n satisfying ``where``, by number of contacts."""
    q = (
        select(ClusterRow.contacts, func.count())
        .where(ClusterRow.n == n, *where)
        .group_by(ClusterRow.contacts)
        .order_by(ClusterRow.contacts)
    )
    return {int(m): int(c) for m, c in s.execute(q)}


def _lattices(s: Session, n: int) -> dict[str, int]:
    q = select(ClusterRow.lattice, func.count()).where(ClusterRow.n == n).group_by(ClusterRow.lattice)
    return {str(k): int(c) for k, c in s.execute(q)}


def _multi_embedding(s: Session, n: int) -> dict[str, int]:
    """{number of geometries: number of contact graphs having that many}, for 2 or more."""
    per_graph = (
        select(func.count().label("k"))
        .where(ClusterRow.n == n)
        .group_by(ClusterRow.certificate)
        .having(func.count() > 1)
        .subquery()
    )
    q = select(per_graph.c.k, func.count()).group_by(per_graph.c.k).order_by(per_graph.c.k)
    return {str(int(k)): int(c) for k, c in s.execute(q)}


def _paths(s: Session, n: int) -> dict:
    """Counts over the paths (attempts with a direction) that start at clusters of n, and the clusters
    of n no path from another cluster reached."""
    src = aliased(ClusterRow)
    sums = (func.coalesce(func.sum(c), 0) for c in (AttemptsRow.paths, AttemptsRow.circular, AttemptsRow.rearranged))
    paths, circular, rearranged = s.execute(
        select(*sums).join(src, src.id == AttemptsRow.source_id).where(src.n == n)
    ).one()
    followed = s.execute(
        select(func.coalesce(func.sum(ExpansionRow.paths), 0))
        .join(ClusterRow, ClusterRow.id == ExpansionRow.cluster_id)
        .where(ClusterRow.n == n)
    ).scalar_one()
    reached_by_path = select(Edge.target_id).where(Edge.target_id != Edge.source_id)
    unreached = (
        s.execute(
            select(ClusterRow.id)
            .where(ClusterRow.n == n, ClusterRow.id.not_in(reached_by_path))
            .order_by(ClusterRow.id)
        )
        .scalars()
        .all()
    )
    return {
        "paths": int(paths),
        "paths_followed": int(followed),
        "circular_paths": int(circular),
        "rearranged_paths": int(rearranged),
        "unreached": list(unreached),
    }


def _gaps(s: Session, n: int) -> list[dict]:
    q = (
        select(ClusterRow.id, ClusterRow.contacts, ClusterRow.min_gap)
        .where(ClusterRow.n == n, ClusterRow.min_gap.is_not(None))
        .order_by(ClusterRow.min_gap, ClusterRow.id)
        .limit(SMALLEST)
    )
    return [{"id": i, "contacts": m, "min_gap": g} for i, m, g in s.execute(q)]


def stats(s: Session, n: int | None = None, every: dict[int, dict[int, int]] | None = None) -> list[dict]:
    """One dict per n (ascending), with the keys documented in the README.

    ``fit`` is the fit of the totals of every n in the database (not only
    ``n``) whose count is complete to b·(n−5)!, and what it predicts for this n.
    ``every`` is ``counts_by_n(s)`` if the caller has it.
    """
    every = counts_by_n(s) if every is None else every
    restricted, partial = incomplete_ns(s)
    fit = fit_all(every, restricted, partial)
    out = []
    for nn, by_contacts in every.items():
        if n is not None and nn != n:
            continue
        total = sum(by_contacts.values())
        iso = 3 * nn - 6
        lattices = _lattices(s, nn)
        unclassified = lattices.pop("None", 0)
        lattices.pop(NOT_CLOSE_PACKED, None)
        gaps = _gaps(s, nn)
        paths = _paths(s, nn)
        singular = _by(s, nn, ClusterRow.singular.is_(True))
        out.append(
            {
                "n": nn,
                "complete": nn not in restricted and nn not in partial,  # a full run of n is complete
                "min_contacts": restricted.get(nn),
                "total": total,
                "by_contacts": {str(m): c for m, c in by_contacts.items()},
                "hypostatic": sum(c for m, c in by_contacts.items() if m < iso),
                "isostatic": by_contacts.get(iso, 0),
                "hyperstatic": sum(c for m, c in by_contacts.items() if m > iso),
                "singular": sum(singular.values()),
                "singular_by_contacts": {str(m): c for m, c in singular.items()},
                "close_packed": sum(lattices.values()),
                "close_packed_by_contacts": {
                    str(m): c
                    for m, c in _by(
                        s, nn, ClusterRow.lattice.is_not(None), ClusterRow.lattice != NOT_CLOSE_PACKED
                    ).items()
                },
                "lattice": dict(sorted(lattices.items())),
                "unclassified": unclassified,
                "multi_embedding": _multi_embedding(s, nn),
                "min_gap": gaps[0]["min_gap"] if gaps else None,
                "smallest_gaps": gaps,
                "circular_paths": paths["circular_paths"],
                "rearranged_paths": paths["rearranged_paths"],
                "paths": paths["paths"],
                "paths_followed": paths["paths_followed"],
                "unreached": paths["unreached"],
                "fit": None
                if fit is None
                else {"b": fit["b"], "predicted": fit["b"] * math.factorial(nn - 5)}
                if nn >= 5
                else None,
                "paper": against_paper(nn, by_contacts, restricted.get(nn)),
            }
        )
    return out


def _titled(title: str, cols: list[str], rows: list[list]) -> str:
    return f"{title}\n{table(cols, rows)}"


def format_stats(d: dict) -> str:
    """The tables of one n, as text."""
    n, iso = d["n"], 3 * d["n"] - 6
    head = (
        f"n = {n}: {counted(d['total'], 'rigid cluster')} ({d['hypostatic']} hypostatic, {d['isostatic']} isostatic, "
        f"{d['hyperstatic']} hyperstatic)"
    )
    if d.get("min_contacts") is not None:
        head = (
            f"n = {n}: {counted(d['total'], 'rigid cluster')} with at least {d['min_contacts']} contacts (runs restricted "
            f"by --min-contacts: not every cluster of n = {n}, and left out of the fit)"
        )
    elif not d["complete"]:
        head = f"n = {n}: {counted(d['total'], 'rigid cluster')} so far (partial: no full run of n = {n} is complete)"
    if d["fit"] is not None:
        head += f"; the fit b·(n−5)! with b = {d['fit']['b']:.3f} gives {d['fit']['predicted']:.0f}"
    paper = (d.get("paper") or {}).get("by_contacts")
    contacts = sorted({int(m) for m in d["by_contacts"]} | {int(m) for m in paper or ()})
    cols = ["contacts", "3n-6+", "clusters"] + (["paper"] if paper is not None else []) + ["singular", "close-packed"]
    rows = [
        [m, f"{m - iso:+d}", d["by_contacts"].get(str(m), 0)]
        + ([paper.get(str(m), 0)] if paper is not None else [])
        + [d["singular_by_contacts"].get(str(m), 0), d["close_packed_by_contacts"].get(str(m), 0)]
        for m in contacts
    ]
    rows.append(
        ["total", "", d["total"]]
        + ([d["paper"]["total"]] if paper is not None else [])
        + [d["singular"], d["close_packed"]]
    )
    parts = [head, _titled("clusters, singular clusters and close-packed fragments by number of contacts:", cols, rows)]
    said = verdict(n, d.get("paper"), d["complete"], d.get("min_contacts"))
    if said is not None:
        parts.append(said)
    if d["close_packed"]:
        parts.append(
            _titled(
                "close-packed fragments by lattice:", ["lattice", "clusters"], [[k, v] for k, v in d["lattice"].items()]
            )
        )
    else:
        parts.append("close-packed fragments: none")
    if d["unclassified"]:
        parts.append(
            f"{counted(d['unclassified'], 'cluster')} {'is' if d['unclassified'] == 1 else 'are'} not classified "
            "yet: run `packings db backfill`"
        )
    if d["multi_embedding"]:
        parts.append(
            _titled(
                "adjacency matrices with more than one geometry:",
                ["geometries", "adjacency matrices"],
                [[k, v] for k, v in d["multi_embedding"].items()],
            )
        )
    else:
        parts.append("adjacency matrices with more than one geometry: none")
    if d["smallest_gaps"]:
        parts.append(f"smallest gap: {d['min_gap']:.6g}")
        parts.append(
            _titled(
                f"the {len(d['smallest_gaps'])} smallest gaps:",
                ["cluster", "contacts", "gap"],
                [[g["id"], g["contacts"], f"{g['min_gap']:.6g}"] for g in d["smallest_gaps"]],
            )
        )
    unreached = d["unreached"]
    shown = ", ".join(map(str, unreached[:10])) + (", ..." if len(unreached) > 10 else "")
    parts.append(
        f"paths (every broken subset and direction, as the paper counts them): {d['paths']}, of which "
        f"{d['paths_followed']} followed (the others taken by symmetry or retraced from their end)\n"
        f"circular paths (back to every sphere's place): {d['circular_paths']}; paths to a permutational isomer "
        f"of their start: {d['rearranged_paths']}; clusters no path reaches: {len(unreached)}"
        + (f" (ids {shown})" if unreached else "")
    )
    return "\n".join(parts)


def fit_all(every: dict[int, dict[int, int]], restricted=(), partial=()) -> dict | None:
    """The fit of the totals of ``counts_by_n`` to b·(n−5)!, leaving out the ``restricted`` n (counts of
    runs restricted by --min-contacts: :func:`packings.service.queries.incomplete_ns`) and the ``partial`` ones
    (no full run complete)."""
    return fit_factorial({k: sum(v.values()) for k, v in every.items() if k not in restricted and k not in partial})


def format_fit(fit: dict | None) -> str:
    """One line on the fit of the totals to b·(n−5)!."""
    if fit is None:
        return "fit of the totals to b·(n−5)!: no n to fit"
    return (
        f"fit of the totals to b·(n−5)!: b = {fit['b']:.3f} over {fit['points']} values of n "
        f"(rms log residual {fit['rms_log_residual']:.3f}; the paper's totals give about 2.5)"
    )
