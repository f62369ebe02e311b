"""The coordinator's work that could grow with the frontier: claims and progress reads, with up to a million pending.

For each size P, a fresh database (SQLite file or PostgreSQL database) holds one run of n with P pending
expansions behind D done ones (``--done``, as a fraction of P), each of its own cluster row (synthetic
rows: what a claim or a progress read touches is the expansions' table and its indexes). Then, for the
schema with and without ``ix_expansions_pending`` (revision 0012; without it is the schema of 0011),
alternated: ``--claims`` claims of ``--k`` expansions by ``packings.service.store.claim``, each claimed
batch then marked done as a write-back would, and as many progress reads as the coordinator makes
(``packings.service.coordinator`` reads the run's counts by status). Printed per P and variant: the
milliseconds a claim and a progress read take, and the resident memory of this process (which runs the
coordinator's code) after filling, after the claims and reads, and their growth.

    python -m benchmarks frontier --backends sqlite postgresql --pending 10000 100000 1000000

PostgreSQL: the database is made through ``PACKINGS_TEST_PG`` (default postgresql://postgres@127.0.0.1:5432/postgres)
and dropped afterwards.
"""

from __future__ import annotations

import json
import os
import time

N = 14  #: the run's n (only a label: the clusters are synthetic)
PENDING_INDEX = "ix_expansions_pending"


def add_arguments(p) -> None:
    p.add_argument("--backends", nargs="+", default=["sqlite", "postgresql"], choices=["sqlite", "postgresql"])
    p.add_argument("--pending", nargs="+", type=int, default=[10_000, 100_000, 1_000_000])
    p.add_argument("--done", type=float, default=0.5, help="done expansions before the pending ones, per pending one")
    p.add_argument("--claims", type=int, default=100, help="claims timed per variant")
    p.add_argument("--k", type=int, default=64, help="expansions a claim takes (4 tasks of 16)")
    p.add_argument("--json", action="store_true")


def _rss_mib() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def fill(engine, run_id: int, pending: int, done: int) -> None:
    """``done`` done and then ``pending`` pending expansions of the run, each of a new synthetic cluster, in
    set-based statements (a series on PostgreSQL, a recursive query on SQLite)."""
    from sqlalchemy import text

    from packings.service.db import is_postgresql

    total = pending + done
    with engine.begin() as c:
        first = c.execute(text("SELECT coalesce(max(id), 0) FROM clusters")).scalar() + 1
        if is_postgresql(engine):
            series = "SELECT generate_series(CAST(:a AS integer), CAST(:b AS integer)) AS i"
            blob = "'\\x00'::bytea"
        else:
            series = "WITH RECURSIVE s(i) AS (SELECT :a UNION ALL SELECT i + 1 FROM s WHERE i < :b) SELECT i FROM s"
            blob = "x'00'"
        bounds = {"a": first, "b": first + total - 1}
        c.execute(
            text(
                "INSERT INTO clusters (id, n, contacts, certificate, embedding, coords, contact_pairs, rigid_kind, "
                "rigid_method, flexes, stresses, singular, found_by, created_at) "
                f"SELECT i, {N}, 36, 'synthetic-' || i, 0, {blob}, {blob}, 'first-order', 'synthetic', 0, 0, "
                f"false, 'path', CURRENT_TIMESTAMP FROM ({series}) AS s"
            ),
            bounds,
        )
        c.execute(
            text(
                "INSERT INTO expansions (run_id, cluster_id, status, attempts, retries, isolated_failures) "
                "SELECT :run, i, CASE WHEN i < :a + :done THEN 'done' ELSE 'pending' END, 0, 0, 0 "
                f"FROM ({series}) AS s"
            ),
            {**bounds, "run": run_id, "done": done},
        )
        if is_postgresql(engine):
            c.execute(text("SELECT setval(pg_get_serial_sequence('clusters', 'id'), (SELECT max(id) FROM clusters))"))
    if is_postgresql(engine):
        with engine.connect().execution_options(isolation_level="AUTOCOMMIT") as c:
            c.execute(text("VACUUM ANALYZE expansions"))
    else:
        with engine.begin() as c:
            c.execute(text("ANALYZE"))


def _with_index(engine, present: bool) -> None:
    """The schema with or without the model's ``ix_expansions_pending``."""
    from packings.service.models import ExpansionRow

    index = next(i for i in ExpansionRow.__table__.indexes if i.name == PENDING_INDEX)
    with engine.begin() as c:
        index.drop(c, checkfirst=True)
        if present:
            index.create(c)


def measure(engine, run_id: int, claims: int, k: int) -> dict:
    """Claims of ``k`` (each batch then marked done) and progress reads, timed; the memory they leave."""
    from sqlalchemy import bindparam, text

    from packings.service import coordinator, store
    from packings.service.db import sessions

    Session_, Reader = sessions(engine), sessions(engine, readonly=True)
    done = text("UPDATE expansions SET status = 'done', lease_owner = NULL, lease_token = NULL WHERE id IN :ids")
    done = done.bindparams(bindparam("ids", expanding=True))
    claim_s = read_s = 0.0
    counts = None
    for _ in range(claims):
        t = time.perf_counter()
        got = store.claim(Session_, run_id, "frontier-benchmark", k)
        claim_s += time.perf_counter() - t
        with engine.begin() as c:
            c.execute(done, {"ids": [i for i, _ in got]})
        t = time.perf_counter()
        counts = coordinator._progress(Reader, run_id)
        read_s += time.perf_counter() - t
    return {
        "claim_ms": round(1000 * claim_s / claims, 3),
        "progress_ms": round(1000 * read_s / claims, 3),
        "pending_after": counts.pending if counts else None,
        "rss_mib": round(_rss_mib(), 1),
    }


def one_size(backend: str, pending: int, args) -> list[dict]:
    from sqlalchemy import text

    from benchmarks.soak import fresh_database
    from packings.service import store
    from packings.service.db import open_database, sessions
    from packings.workers.params import Params

    done = int(pending * args.done)
    rows = []
    with fresh_database(backend) as url:
        engine = open_database(url, create=True)
        try:
            info = store.start_run(sessions(engine), N, Params(), "frontier-benchmark")
            with engine.begin() as c:  # the seed's expansion is not one of the P
                c.execute(text("UPDATE expansions SET status = 'done' WHERE run_id = :r"), {"r": info.id})
            t = time.perf_counter()
            fill(engine, info.id, pending, done)
            filled_s = time.perf_counter() - t
            rss0 = _rss_mib()
            # without the index first, then with it, then without and with again: each variant twice,
            # alternated (the later rounds see a few more expansions done)
            for present in (False, True, False, True):
                _with_index(engine, present)
                m = measure(engine, info.id, args.claims, args.k)
                rows.append(
                    {
                        "backend": backend,
                        "pending": pending,
                        "done": done,
                        "index": present,
                        "fill_s": round(filled_s, 1),
                        "rss_filled_mib": round(rss0, 1),
                        **m,
                        "rss_growth_mib": round(m["rss_mib"] - rss0, 1),
                    }
                )
        finally:
            engine.dispose()
    return rows


def run(args) -> int:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    rows = [r for backend in args.backends for p in args.pending for r in one_size(backend, p, args)]
    if args.json:
        print(json.dumps({"rows": rows}, indent=1))
        return 0
    print(
        "| backend | pending | done | ix_expansions_pending | ms a claim | ms a progress read | RSS MiB | growth MiB |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['backend']} | {r['pending']:,} | {r['done']:,} | {'yes' if r['index'] else 'no'} | "
            f"{r['claim_ms']:.2f} | {r['progress_ms']:.2f} | {r['rss_mib']:.0f} | {r['rss_growth_mib']:+.1f} |"
        )
    return 0
