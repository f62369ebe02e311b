"""A run's rate by class and number of contacts, its database's size, and its projected total.

For the newest run of ``--n`` in ``--db URL`` (or ``--run ID``), complete or still going (a run in
progress reads as any other: its expansions done so far): for each number of contacts m and class
(``benchmarks.classes.cluster_class``) the clusters stored, those expanded and their mean and total time
in ``expand`` (``expansions.seconds``); the run's expansions by status and its coordinator wall time
(``runs.seconds``), with the rate over the whole run and over its last ``--window`` minutes of
write-backs (fewer if the run has written back for less), and by class over that window too (``lately``); the database's size (the SQLite file with its write-ahead log, or PostgreSQL's
``pg_database_size``) and its bytes per stored cluster.

Where the paper counted n (``packings.service.paper``), the projection: every cluster of each m
expanded at the mean time of those of m the run has expanded (its classes pooled as the run met
them), divided among ``--workers``; and the clusters left at the recent rate.  Both lean high early in
a run: a cluster expanded later is given more of the paths that arrived at it (docs/method.md) and
follows fewer; an m the run has not expanded yet is left out and listed.
"""

from __future__ import annotations

import datetime as dt
import json
import os

from benchmarks.classes import CLASSES, cluster_class


def add_arguments(p) -> None:
    p.add_argument("--db", required=True, metavar="URL", help="a catalogue holding the run")
    p.add_argument("--n", type=int, required=True, help="the number of spheres")
    p.add_argument("--run", type=int, default=None, metavar="ID", help="the run (default: the newest of n)")
    p.add_argument("--workers", type=int, default=2, help="workers the projection divides among (default 2)")
    p.add_argument("--window", type=float, default=10.0, metavar="MIN", help="minutes of the recent rate (default 10)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def database_bytes(engine) -> int | None:
    """The database's size on disk: a SQLite file with its write-ahead log, or PostgreSQL's database."""
    from sqlalchemy import text

    if engine.dialect.name == "sqlite":
        path = engine.url.database
        if not path or path == ":memory:":
            return None
        return sum(os.path.getsize(p) for p in (path, path + "-wal") if os.path.exists(p))
    if engine.dialect.name == "postgresql":
        with engine.connect() as c:
            return int(c.execute(text("SELECT pg_database_size(current_database())")).scalar())
    return None


def report(url: str, n: int, run_id: int | None = None, workers: int = 2, window: float = 10.0) -> dict:
    from sqlalchemy import func, select

    import packings
    from packings.service.models import DONE, ClusterRow, ExpansionRow, Run
    from packings.service.paper import by_contacts

    with packings.connect(url) as cat, cat.session() as s:
        q = select(Run).where(Run.n == n)
        q = q.where(Run.id == run_id) if run_id is not None else q.order_by(Run.id.desc()).limit(1)
        run = s.execute(q).scalars().first()
        if run is None:
            raise SystemExit(f"no run of n = {n}" + (f" with id {run_id}" if run_id is not None else "") + f" in {url}")
        stored: dict[tuple[int, str], int] = {}
        for m, flexes, k in s.execute(
            select(ClusterRow.contacts, ClusterRow.flexes, func.count())
            .where(ClusterRow.n == n)
            .group_by(ClusterRow.contacts, ClusterRow.flexes)
        ):
            key = (m, cluster_class(n, m, flexes))
            stored[key] = stored.get(key, 0) + k
        done = _expanded(s, n, run.id)
        status = dict(
            s.execute(
                select(ExpansionRow.status, func.count())
                .where(ExpansionRow.run_id == run.id)
                .group_by(ExpansionRow.status)
            ).all()
        )
        first, last = s.execute(
            select(func.min(ExpansionRow.finished_at), func.max(ExpansionRow.finished_at)).where(
                ExpansionRow.run_id == run.id
            )
        ).one()
        recent, span, lately = 0, 0.0, {}
        if last is not None:
            since = max(first, last - dt.timedelta(minutes=window))
            span = (last - since).total_seconds()
            lately = _expanded(s, n, run.id, since)
            recent = sum(k for k, _ in lately.values())
        size = database_bytes(cat.engine)
    rows = []
    for m, cls in sorted(set(stored) | set(done), key=lambda k: (k[0], CLASSES.index(k[1]))):
        k, seconds = done.get((m, cls), (0, 0.0))
        k_late, s_late = lately.get((m, cls), (0, 0.0))
        rows.append(
            {
                "contacts": m,
                "class": cls,
                "stored": stored.get((m, cls), 0),
                "expanded": k,
                "seconds": seconds,
                "mean_s": seconds / k if k else None,
                "recent_expanded": k_late,
                "recent_mean_s": s_late / k_late if k_late else None,
            }
        )
    clusters = sum(stored.values())
    out = {
        "n": n,
        "run": run.id,
        "status": run.status,
        "run_seconds": run.seconds,
        "expansions": status,
        "clusters": clusters,
        "rows": rows,
        "rate": status.get(DONE, 0) / run.seconds if run.seconds else None,
        "recent_rate": recent / span if recent and span else None,
        "window_minutes": span / 60.0,
        "database_bytes": size,
        "bytes_per_cluster": size / clusters if size and clusters else None,
    }
    paper = by_contacts(n)
    if paper:
        out["projection"] = projection(paper, rows, workers, out["recent_rate"], status.get(DONE, 0))
    return out


def _expanded(s, n: int, run_id: int, since: dt.datetime | None = None) -> dict[tuple[int, str], list]:
    """{(contacts, class): [expansions done, seconds in expand]} of run ``run_id``, those written back since
    ``since`` if given."""
    from sqlalchemy import func, select

    from packings.service.models import DONE, ClusterRow, ExpansionRow

    q = (
        select(ClusterRow.contacts, ClusterRow.flexes, func.count(), func.sum(ExpansionRow.seconds))
        .join(ClusterRow, ClusterRow.id == ExpansionRow.cluster_id)
        .where(ExpansionRow.run_id == run_id, ExpansionRow.status == DONE)
        .group_by(ClusterRow.contacts, ClusterRow.flexes)
    )
    if since is not None:
        q = q.where(ExpansionRow.finished_at >= since)
    out: dict[tuple[int, str], list] = {}
    for m, flexes, k, seconds in s.execute(q):
        d = out.setdefault((m, cluster_class(n, m, flexes)), [0, 0.0])
        d[0] += k
        d[1] += seconds or 0.0
    return out


def projection(paper: dict[int, int], rows: list[dict], workers: int, recent_rate: float | None, done: int) -> dict:
    """Every cluster of the paper's counts expanded at the run's mean time of its m, on ``workers``; and
    the paper's total left at the recent rate.  The m the run has not expanded yet are listed apart."""
    by_m: dict[int, list] = {}
    for r in rows:
        d = by_m.setdefault(r["contacts"], [0, 0.0])
        d[0] += r["expanded"]
        d[1] += r["seconds"]
    seconds, unseen = 0.0, {}
    per_m = {}
    for m, count in sorted(paper.items()):
        k, s = by_m.get(m, (0, 0.0))
        if k:
            per_m[m] = count * s / k
            seconds += per_m[m]
        else:
            unseen[m] = count
    total = sum(paper.values())
    return {
        "expand_seconds_by_contacts": per_m,
        "expand_seconds": seconds,
        "hours_on_workers": seconds / workers / 3600.0,
        "workers": workers,
        "not_yet_expanded": unseen,
        "paper_total": total,
        "hours_left_at_recent_rate": (total - done) / recent_rate / 3600.0 if recent_rate else None,
    }


def run(args) -> int:
    r = report(args.db, args.n, args.run, args.workers, args.window)
    if args.json:
        print(json.dumps(r, indent=2, default=str))
        return 0
    ex = r["expansions"]
    print(
        f"n = {r['n']}, run {r['run']} ({r['status']}): {r['clusters']:,} clusters stored; expansions "
        + ", ".join(f"{k} {v:,}" for k, v in sorted(ex.items()))
        + f"; coordinator wall {r['run_seconds']:.0f} s"
    )
    if r["rate"]:
        print(f"rate: {r['rate']:.2f} expansions/s over the run", end="")
        if r["recent_rate"]:
            print(f", {r['recent_rate']:.2f} over its last {r['window_minutes']:g} min", end="")
        print()
    if r["database_bytes"]:
        print(f"database: {r['database_bytes'] / 2**20:,.1f} MiB, {r['bytes_per_cluster']:,.0f} B a stored cluster")
    print(f"{'m':>3} {'class':<12}{'stored':>10}{'expanded':>10}{'mean s':>9}{'total s':>10}{'lately':>8}{'mean s':>9}")
    for row in r["rows"]:
        mean, late = (f"{row[k]:.3f}" if row[k] is not None else "-" for k in ("mean_s", "recent_mean_s"))
        print(
            f"{row['contacts']:>3} {row['class']:<12}{row['stored']:>10,}{row['expanded']:>10,}{mean:>9}"
            f"{row['seconds']:>10.0f}{row['recent_expanded']:>8,}{late:>9}"
        )
    print(f"(lately: the expansions written back in the last {r['window_minutes']:.1f} min, and their mean)")
    p = r.get("projection")
    if p:
        print(
            f"projection to the paper's {p['paper_total']:,}: {p['expand_seconds']:,.0f} s in expand, "
            f"{p['hours_on_workers']:.1f} h on {p['workers']} workers"
            + (
                f"; at the recent rate {p['hours_left_at_recent_rate']:.1f} h left"
                if p["hours_left_at_recent_rate"]
                else ""
            )
        )
        if p["not_yet_expanded"]:
            print(
                "  not in it (no cluster of that m expanded yet): "
                + ", ".join(f"m = {m}: {c:,}" for m, c in p["not_yet_expanded"].items())
            )
    return 0
