"""Paths of a complete run that retrace another path of it: how many, from a stored catalogue.

A path from a first-order rigid cluster A that breaks contacts and ends at a first-order rigid cluster
B by forming contacts lies on a curve that B's path breaking the contacts formed follows back to A, so
a run following every path follows that curve twice (docs/method.md).  From the transitions of the
newest complete, unrestricted run of n in ``--db URL``: the
attempts with a direction, those a run may take from the other end (between two first-order rigid
clusters, one of them regular: docs/method.md), and their ordered
pairs of clusters (A, B).  Counted from each end up to that end's symmetries, the paths A -> B and B -> A of
one pair obey k(A -> B) |Sym(B)| = k(B -> A) |Sym(A)| (``identity.symmetries``, reflections
included); the pairs that do not, or that have no reverse at all, are where a path back ended
otherwise.  ``retracing`` sums min(k(A -> B), k(B -> A)) over the pairs that obey it: the paths a run
could take from the other end instead of following them, against the paths a run following every one
would follow (``paths_followed`` + ``paths_retraced``).  ``paths_retraced`` are those the run did take
from the other end (``expand`` with arrivals: docs/method.md).
"""

from __future__ import annotations

import json
from collections import Counter


def add_arguments(p) -> None:
    p.add_argument("--n", type=int, required=True, help="the number of spheres")
    p.add_argument("--db", required=True, metavar="URL", help="a catalogue holding a complete run of N")
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def count(url: str, n: int) -> dict:
    """The report (see the module's doc) for the newest complete run of ``n`` in ``url``."""
    from sqlalchemy import func, select

    import packings
    from packings.service.models import COMPLETE, AttemptsRow, ClusterRow, ExpansionRow, Run, core_cluster
    from packings.service.queries import transitions
    from packings.workers.identity import symmetries
    from packings.workers.outcomes import RIGID
    from packings.workers.params import Params

    with packings.connect(url) as cat, cat.session() as s:
        runs = [
            (rid, json.loads(params))
            for rid, params in s.execute(
                select(Run.id, Run.params).where(Run.n == n, Run.status == COMPLETE).order_by(Run.id.desc())
            )
        ]
        runs = [(rid, params) for rid, params in runs if params.get("min_contacts") is None]
        if not runs:
            raise SystemExit(f"no complete run of n = {n} (without --min-contacts) in {url}")
        run_id, params = runs[0]
        tol_d = Params.from_dict(params).tol_d
        rigid, regular = {}, set()  # the first-order rigid clusters; the regular ones among them
        for cid, m, coords, contacts in s.execute(
            select(ClusterRow.id, ClusterRow.contacts, ClusterRow.coords, ClusterRow.contact_list).where(
                ClusterRow.n == n, ClusterRow.contacts >= 3 * n - 6, ClusterRow.flexes == 0
            )
        ):
            rigid[cid] = (coords, contacts)
            if m == 3 * n - 6:
                regular.add(cid)
        followed = s.execute(select(func.sum(ExpansionRow.paths)).where(ExpansionRow.run_id == run_id)).scalar() or 0
        retraced = sum(
            json.loads(o).get("paths_retraced", 0)
            for o in s.execute(
                select(ExpansionRow.outcomes).where(ExpansionRow.run_id == run_id, ExpansionRow.outcomes.is_not(None))
            ).scalars()
        )
        with_direction = s.execute(select(func.sum(AttemptsRow.paths)).where(AttemptsRow.run_id == run_id)).scalar()
        k = Counter()
        for t in transitions(s, run=run_id):
            if t.direction == 0 or t.outcome != RIGID:
                continue
            source, target = t.source_id, t.target_id
            if (
                source in rigid
                and target in rigid
                and (source in regular or target in regular)
                and t.broken
                and t.new_contacts
            ):
                k[(source, target)] += 1
    order = {cid: len(symmetries(core_cluster(n, *rigid[cid]), tol_d)) for cid in {c for pair in k for c in pair}}
    holds = fails = lonely = retracing = 0
    for (a, b), forth in k.items():
        back = k.get((b, a), 0)
        if back == 0:
            lonely += 1
        elif forth * order[b] == back * order[a]:
            holds += 1
            if a < b:
                retracing += min(forth, back)
        else:
            fails += 1
    every = int(followed) + retraced
    return {
        "n": n,
        "run": run_id,
        "attempts_with_direction": with_direction,
        "paths_followed": int(followed),
        "paths_retraced": retraced,
        "retraceable": sum(k.values()),
        "ordered_pairs": len(k),
        "rule_holds": holds,
        "rule_fails": fails,
        "no_reverse": lonely,
        "retracing": retracing,
        "retracing_share": round(retracing / every, 4) if every else 0.0,
    }


def run(args) -> int:
    report = count(args.db, args.n)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    r = report
    print(
        f"n = {r['n']}, run {r['run']}: {r['attempts_with_direction']} attempts with a direction, "
        f"{r['paths_followed']} paths followed, {r['paths_retraced']} taken from the other end"
    )
    print(
        f"  between first-order rigid clusters, one of them regular: {r['retraceable']} attempts, "
        f"{r['ordered_pairs']} ordered pairs of clusters"
    )
    print(
        f"  pairs whose paths are each other's reverses (k(A->B)|Sym(B)| = k(B->A)|Sym(A)|): {r['rule_holds']}; "
        f"other counts: {r['rule_fails']}; no reverse: {r['no_reverse']}"
    )
    print(
        f"  paths a run could take from the other end: {r['retracing']} "
        f"({100 * r['retracing_share']:.1f} % of the paths followed and taken from the other end)"
    )
    return 0
