"""Reading the catalogue back: the stored attempts (:func:`transitions`), the paths a task may retrace
(:func:`arrivals_at`), what the database holds about a cluster besides its row (:func:`links`), the counts
by n and contacts, the minimum gaps, the n whose counts are not a full run's, and a run's state (its frontier,
faults, counts and diagnostics, its status as shown).

Reads only, of any session or connection: the transactions that write (the write-back, runs, claims and
leases) are :mod:`packings.service.store`'s.  The packed attempts are unpacked by
:mod:`packings.service.paths_codec`; counting paths reads the counts of ``attempts`` and ``edges``, never
packed data (docs/architecture.md).
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from typing import Iterator

from sqlalchemy import Connection, bindparam, func, select
from sqlalchemy.orm import Session

from packings.service.models import COMPLETE, DONE, FAILED, RUNNING, AttemptsRow, ClusterRow, Edge, ExpansionRow, Run
from packings.service.owners import coordinator_alive
from packings.service.paths_codec import Packed, unpack

_A, _EDGES = AttemptsRow.__table__, Edge.__table__
#: the expansions with paths that arrived at these clusters and can be retraced from them (edges.labelled),
#: in the order they were written (the arrivals' order: packings.workers.expand.arrivals keeps the first
#: of each set of contacts)
_ARRIVALS_DATA = (
    select(_EDGES.c.target_id, _A.c.run_id, _A.c.source_id, _A.c.id, _A.c.data)
    .join_from(_EDGES, _A, (_A.c.source_id == _EDGES.c.source_id) & (_A.c.run_id == _EDGES.c.run_id))
    .where(
        _EDGES.c.target_id.in_(bindparam("cids", expanding=True)),
        _EDGES.c.run_id.in_(bindparam("runs", expanding=True)),
        _EDGES.c.labelled > 0,
    )
    .order_by(_A.c.id)
)


# --------------------------------------------------------------------------- attempts


@dataclass(frozen=True)
class Transition:
    """One attempt as it is read back: what a row of the former ``transitions`` table held, with the
    expansion's ``attempts`` row (``row``, in order of writing) and the attempt's place in it (``attempt``)."""

    row: int
    attempt: int
    run_id: int
    source_id: int
    broken: tuple[tuple[int, int], ...]
    direction: int
    outcome: str
    target_id: int | None
    steps: int
    new_contacts: tuple[tuple[int, int], ...]
    labels: tuple[int, ...] | None


def transitions(
    s: Session | Connection,
    *,
    source: int | None = None,
    target: int | None = None,
    run: int | None = None,
    n: int | None = None,
) -> Iterator[Transition]:
    """The stored attempts, in the order they were written: those from cluster ``source``, those that
    reached cluster ``target`` (read through ``edges``: only the expansions that reached it are unpacked),
    those of ``run``, those from the clusters of ``n`` spheres; all of them when none is given."""
    q = select(_A.c.id, _A.c.run_id, _A.c.source_id, _A.c.data).order_by(_A.c.id)
    if target is not None:
        q = q.join(_EDGES, (_EDGES.c.source_id == _A.c.source_id) & (_EDGES.c.run_id == _A.c.run_id)).where(
            _EDGES.c.target_id == target
        )
    if source is not None:
        q = q.where(_A.c.source_id == source)
    if run is not None:
        q = q.where(_A.c.run_id == run)
    if n is not None:
        q = q.join(ClusterRow, ClusterRow.id == _A.c.source_id).where(ClusterRow.n == n)
    for row, run_id, source_id, data in s.execute(q):
        p = unpack(data)
        for k in range(len(p)) if target is None else p.to(target):
            a = p.attempt(int(k))
            yield Transition(
                row,
                int(k),
                run_id,
                source_id,
                a.broken,
                a.direction,
                a.outcome,
                a.target,
                a.steps,
                a.new_contacts,
                a.labels,
            )


def arrivals_at(s: Session | Connection, wanted: set[tuple[int, int]]) -> dict[tuple[int, int], list[tuple]]:
    """The paths of run r that arrived at cluster c with the endpoint's labels, for each (r, c) in ``wanted``:
    rows (source id, broken, new contacts, steps, labels) as :func:`packings.workers.expand.arrivals` takes
    them, in the order they were written.  Only the packed attempts of the expansions that reached c
    (edges.labelled) are read."""
    came: dict[tuple[int, int], list[tuple]] = {}
    if not wanted:
        return came
    packed: dict[int, Packed] = {}
    for target, run_id, source, aid, data in s.execute(
        _ARRIVALS_DATA, {"cids": sorted({c for _, c in wanted}), "runs": sorted({r for r, _ in wanted})}
    ):
        if (run_id, target) not in wanted:
            continue
        p = packed.get(aid)
        if p is None:
            p = packed[aid] = unpack(data)
        out = came.setdefault((run_id, target), [])
        for k in p.to(target, labelled=True):
            a = p.one(int(k))
            out.append((source, a.broken, a.new_contacts, a.steps, a.labels))
    return came


def links(s: Session, cluster_id: int) -> dict:
    """What the database holds about a cluster besides its row: the paths
    leaving it (by outcome), the paths reaching it, and the runs whose frontier
    holds it."""
    leaving = dict(sorted(Counter(t.outcome for t in transitions(s, source=cluster_id) if t.direction != 0).items()))
    reaching, sources = s.execute(
        select(func.coalesce(func.sum(Edge.paths), 0), func.count(Edge.source_id.distinct())).where(
            Edge.target_id == cluster_id
        )
    ).one()
    runs = [
        {"run": r, "n": n, "run_status": rs, "expansion": es, "paths": p}
        for r, n, rs, es, p in s.execute(
            select(ExpansionRow.run_id, Run.n, Run.status, ExpansionRow.status, ExpansionRow.paths)
            .join(Run, Run.id == ExpansionRow.run_id)
            .where(ExpansionRow.cluster_id == cluster_id)
            .order_by(ExpansionRow.run_id)
        )
    ]
    return {
        "paths_leaving": sum(leaving.values()),
        "leaving_by_outcome": leaving,
        "paths_reaching": int(reaching),
        "reached_from": sources,
        "runs": runs,
    }


# --------------------------------------------------------------------------- counts


def incomplete_ns(s: Session) -> tuple[dict[int, int], set[int]]:
    """The n whose counts are not the method's full count of n, never to be mixed with full counts (the fit,
    the totals), from one read of the runs:

    - restricted: {n: the fewest contacts kept} for each n whose clusters come only from runs restricted by
      ``--min-contacts`` (no run of n keeps every cluster): their counts are of the clusters with that many
      contacts or more;
    - partial: the other n with stored clusters of which no run that keeps every cluster (no
      ``--min-contacts``, no ``--max-break`` cap) is complete (a run going on or interrupted, a catalysis
      pass's, no run at all)."""
    full: set[int] = set()
    complete: set[int] = set()
    least: dict[int, int] = {}
    for n, status, params in s.execute(select(Run.n, Run.status, Run.params)):
        p = json.loads(params)
        m = p.get("min_contacts")
        if m is None:
            full.add(n)
            if status == COMPLETE and p.get("max_break") is None:
                complete.add(n)
        else:
            least[n] = min(m, least.get(n, m))
    restricted = {n: m for n, m in sorted(least.items()) if n not in full}
    held = set(s.execute(select(ClusterRow.n).distinct()).scalars())
    return restricted, held - complete - set(restricted)


def counts_by_n(s: Session, n: int | None = None) -> dict[int, dict[int, int]]:
    """All stored clusters: {n: {contacts: count}}."""
    q = select(ClusterRow.n, ClusterRow.contacts, func.count()).group_by(ClusterRow.n, ClusterRow.contacts)
    if n is not None:
        q = q.where(ClusterRow.n == n)
    out: dict[int, dict[int, int]] = {}
    for nn, m, c in s.execute(q.order_by(ClusterRow.n, ClusterRow.contacts)):
        out.setdefault(int(nn), {})[int(m)] = int(c)
    return out


def min_gaps(s: Session, ns: set[int] | None = None) -> dict[int, list[float]]:
    """{n: [min_gap, ...]} of the stored clusters that have one, each n's in increasing order (only ``ns`` if
    given)."""
    q = select(ClusterRow.n, ClusterRow.min_gap).where(ClusterRow.min_gap.is_not(None))
    if ns is not None:
        q = q.where(ClusterRow.n.in_(sorted(ns)))
    out: dict[int, list[float]] = {}
    for n, gap in s.execute(q.order_by(ClusterRow.n, ClusterRow.min_gap)):
        out.setdefault(int(n), []).append(float(gap))
    return out


# --------------------------------------------------------------------------- runs

INTERRUPTED = "interrupted"  #: how a run marked running whose coordinator is gone is shown


def shown_status(run: Run) -> str:
    """The run's status as ``status`` and the dashboard show it: :data:`INTERRUPTED` for one marked
    running that no live coordinator drives (the same command resumes it)."""
    if run.status == RUNNING and not coordinator_alive(run.coordinator, run.heartbeat_at):
        return INTERRUPTED
    return run.status


def frontier(s: Session, run_id: int) -> dict[str, int]:
    rows = s.execute(
        select(ExpansionRow.status, func.count()).where(ExpansionRow.run_id == run_id).group_by(ExpansionRow.status)
    ).all()
    return {status: count for status, count in rows}


def faults(s: Session, run_id: int) -> dict[str, int]:
    """The run's infrastructure retries (expansions put back, uncounted) and isolated failures."""
    retries, isolated = s.execute(
        select(
            func.coalesce(func.sum(ExpansionRow.retries), 0), func.coalesce(func.sum(ExpansionRow.isolated_failures), 0)
        ).where(ExpansionRow.run_id == run_id)
    ).one()
    return {"retries": int(retries), "isolated_failures": int(isolated)}


# What a run has found so far: the coordinator's report when it ends, the dashboard's while it runs.


def run_counts(s: Session, run_id: int) -> dict[int, int]:
    """Clusters reached by the run, by number of contacts."""
    rows = s.execute(
        select(ClusterRow.contacts, func.count())
        .join(ExpansionRow, ExpansionRow.cluster_id == ClusterRow.id)
        .where(ExpansionRow.run_id == run_id)
        .group_by(ClusterRow.contacts)
        .order_by(ClusterRow.contacts)
    ).all()
    return {int(m): int(c) for m, c in rows}


def run_diagnostics(s: Session, run_id: int) -> dict:
    """Sums over the run's expansions of what happened to every subset tried."""
    total: Counter = Counter()
    paths = 0
    for outcomes, p in s.execute(
        select(ExpansionRow.outcomes, ExpansionRow.paths).where(
            ExpansionRow.run_id == run_id, ExpansionRow.status == DONE
        )
    ):
        total.update(json.loads(outcomes))
        paths += p or 0
    f = frontier(s, run_id)
    widened = total.pop("widened_paths", 0)
    images = total.pop("paths_by_symmetry", 0)
    retraced = total.pop("paths_retraced", 0)
    return {
        "expansions": f.get(DONE, 0),
        "paths_followed": paths,
        "paths_by_symmetry": images,
        "paths_retraced": retraced,
        "widened_paths": widened,
        **dict(sorted(total.items())),
        "failed_tasks": f.get(FAILED, 0),
    }
