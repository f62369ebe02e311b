"""Soak test: an enumeration under injected faults against an undisturbed one, on each backend.

For each backend, three runs of ``packings enumerate N`` on fresh databases: undisturbed; with one
of the local cluster's worker processes killed (SIGKILL) every 1-3 s; and with the coordinator
killed (SIGKILL) at five moments and the same command run again each time.  Moments come from
``--seed``.  Dask's ``allowed-failures`` is set to ``--allowed-failures`` (default 1) so that a task
hit by that many kills plus one reaches the coordinator as ``KilledWorker``.  Prints a table: faults
injected, clusters expected (the undisturbed run's) against seen, failed, left leased, duplicate
keys, retries, isolated failures, and the wall time against the undisturbed run's; under it, each
kind of faults' runs that stopped early (exit status not 0) out of those made, and the last line of
each such run.  ``--repeat R`` makes each kind of faults ``--faults`` asks for R times, each on a
fresh database (the same undisturbed run the reference).

    python -m benchmarks soak --n 10 [--backends sqlite,postgresql] [--faults workers,coordinator]
                              [--repeat 1] [--seed 1] [--json]
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from contextlib import contextmanager
from pathlib import Path

PG_ADMIN = os.environ.get("PACKINGS_TEST_PG", "postgresql://postgres@127.0.0.1:5432/postgres")


def add_arguments(p) -> None:
    p.add_argument("--n", type=int, default=10)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--backends", default="sqlite,postgresql")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--allowed-failures", type=int, default=1)
    p.add_argument("--faults", default="workers,coordinator", help="kinds of faults: workers, coordinator")
    p.add_argument("--repeat", type=int, default=1, help="runs of each kind of faults, each on a fresh database")
    p.add_argument("--json", action="store_true")


def worker_processes(pid: int) -> list:
    """The Dask worker processes a LocalCluster started under ``pid`` (spawned, or forked from the fork
    server, which is left out: it is their parent)."""
    import psutil

    def command(p) -> str:
        try:
            return " ".join(p.cmdline())
        except psutil.Error:  # gone meanwhile (killed, or its nanny replacing it)
            return ""

    def children(p) -> list:
        try:
            return p.children()
        except psutil.Error:
            return []

    try:
        root = psutil.Process(pid)
        kids = root.children(recursive=True)
    except psutil.Error:
        return []
    kids = [
        p
        for p in kids
        if ("multiprocessing" in command(p) or "spawn_main" in command(p)) and "resource_tracker" not in command(p)
    ]
    # never the fork server (a child of pid whose command says so), even when it has no worker left
    server = {p.pid for p in children(root) if "forkserver" in command(p)}
    pids = {p.pid for p in kids}
    return [p for p in kids if p.pid not in server and not any(c.pid in pids for c in children(p))]


@contextmanager
def postgresql_database(admin_url: str, prefix: str):
    """A new, empty PostgreSQL database (its URL) made through ``admin_url``, dropped on leaving."""
    from sqlalchemy import create_engine, text

    from packings.service.db import parse_url

    name = f"{prefix}_{uuid.uuid4().hex[:12]}"
    admin = create_engine(parse_url(admin_url), isolation_level="AUTOCOMMIT")
    with admin.connect() as c:
        c.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield parse_url(admin_url).set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@contextmanager
def fresh_database(backend: str):
    """The URL of an empty database on ``backend``, removed afterwards."""
    if backend == "sqlite":
        with tempfile.TemporaryDirectory() as d:
            yield f"sqlite:///{Path(d) / 'soak.db'}"
        return
    with postgresql_database(PG_ADMIN, "packings_soak") as url:
        yield url


def _command(n: int, url: str, workers: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "packings.service.cli",
        "enumerate",
        str(n),
        "--db",
        url,
        "--workers",
        str(workers),
        "--quiet",
    ]


def _done(url: str) -> int:
    from sqlalchemy import text

    from packings.service.db import make_engine

    engine = make_engine(url)
    try:
        with engine.connect() as c:
            return c.execute(text("SELECT count(*) FROM expansions WHERE status = 'done'")).scalar()
    except Exception:  # noqa: BLE001 - no schema yet
        return 0
    finally:
        engine.dispose()


def _wait_until(predicate, proc) -> bool:
    while not predicate():
        if proc.poll() is not None:
            return False
        time.sleep(0.05)
    return True


def _last_line(text: str) -> str:
    lines = text.strip().splitlines()
    return lines[-1] if lines else ""


def undisturbed(n: int, url: str, workers: int) -> tuple[int, str]:
    """(exit status, the last line the run wrote on standard error: why it stopped, if it failed)."""
    r = subprocess.run(_command(n, url, workers), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    return r.returncode, _last_line(r.stderr)


def kill_workers(n: int, url: str, workers: int, rng: random.Random) -> tuple[int, int, str]:
    """One worker process killed every 1-3 s from the first expansion done on; (kills, exit status, last
    line on standard error)."""
    with tempfile.TemporaryFile("w+") as err:  # a file, not a pipe: a long run's log must not fill it and block
        proc = subprocess.Popen(_command(n, url, workers), stdout=subprocess.DEVNULL, stderr=err, text=True)
        kills = _kill_workers_of(proc, url, rng)
        status = proc.wait()
        err.seek(0)
        return kills, status, _last_line(err.read())


def _kill_workers_of(proc, url: str, rng: random.Random) -> int:
    kills = 0
    _wait_until(lambda: _done(url) >= 1, proc)
    while proc.poll() is None:
        try:
            proc.wait(timeout=rng.uniform(1.0, 3.0))
            break
        except subprocess.TimeoutExpired:
            pass
        try:
            victims = sorted(worker_processes(proc.pid), key=lambda p: p.pid)
            if victims:
                rng.choice(victims).send_signal(signal.SIGKILL)
                kills += 1
        except Exception:  # noqa: BLE001 - gone already
            pass
    return kills


def kill_coordinator(n: int, url: str, workers: int, rng: random.Random, total: int) -> tuple[int, int, str]:
    """The coordinator killed at five moments (expansions done), rerun each time; (kills, and the exit
    status and last line on standard error of the last run)."""
    kills = 0
    for moment in sorted(rng.sample(range(1, max(total - 1, 6)), 5)):
        proc = subprocess.Popen(_command(n, url, workers), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if _wait_until(lambda: _done(url) >= moment, proc):
            proc.send_signal(signal.SIGKILL)
            kills += 1
        proc.wait()
    return (kills, *undisturbed(n, url, workers))


def inspect(url: str, n: int) -> dict:
    """What the database holds after a run: its clusters' certificates and the fault counts."""
    from sqlalchemy import text

    from packings.service.db import make_engine

    engine = make_engine(url)
    with engine.connect() as c:
        certs = sorted(c.execute(text("SELECT certificate FROM clusters WHERE n = :n"), {"n": n}).scalars())
        dup = c.execute(
            text(
                "SELECT count(*) FROM (SELECT n, certificate, embedding FROM clusters "
                "GROUP BY n, certificate, embedding HAVING count(*) > 1) d"
            )
        ).scalar()
        row = c.execute(
            text(
                "SELECT sum(CASE WHEN status = 'failed' THEN 1 ELSE 0 END), "
                "sum(CASE WHEN status = 'leased' THEN 1 ELSE 0 END), "
                "sum(CASE WHEN status = 'pending' THEN 1 ELSE 0 END), "
                "sum(retries), sum(isolated_failures) FROM expansions"
            )
        ).one()
    engine.dispose()
    return {
        "certificates": certs,
        "duplicates": dup,
        "failed": int(row[0] or 0),
        "leased": int(row[1] or 0),
        "pending": int(row[2] or 0),
        "retries": int(row[3] or 0),
        "isolated_failures": int(row[4] or 0),
    }


def run(args) -> int:
    """The soak of every backend of ``--backends``: its table, or with ``--json`` one JSON object; 0 if every run
    ended well with the undisturbed run's clusters and nothing failed, left leased or pending, or duplicated."""
    unknown = sorted({k.strip() for k in args.faults.split(",")} - {"workers", "coordinator", ""})
    if unknown:
        raise SystemExit(f"soak: unknown kind of faults {', '.join(unknown)} (workers, coordinator)")
    rng = random.Random(args.seed)
    os.environ["DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES"] = str(args.allowed_failures)
    rows, ok = [], True
    for backend in args.backends.split(","):
        runs, expected = _backend_runs(args, backend, rng)
        ok &= _check(runs, expected)  # each backend's runs against its own undisturbed run
        rows.extend(runs)
    early = {}  #: (backend, faults): [runs that stopped early, runs]
    for r in rows:
        e = early.setdefault(f"{r['backend']}, {r['faults']}", [0, 0])
        e[0] += r["exit"] != 0
        e[1] += 1
    if args.json:
        print(json.dumps({"n": args.n, "seed": args.seed, "rows": rows, "early_stops": early}))
    else:
        _print_table(args, rows, early)
    return 0 if ok else 1


def _row(backend: str, faults: str, injected: int, status: int, line: str, seen: dict, seconds: float, ratio) -> dict:
    """One run's row: what it injected, how it ended and what its database holds (:func:`inspect`)."""
    return {
        "backend": backend,
        "faults": faults,
        "injected": injected,
        "exit": status,
        **seen,
        "seconds": round(seconds, 1),
        "time_ratio": ratio,
        "stopped": line if status else "",
    }


def _backend_runs(args, backend: str, rng: random.Random) -> tuple[list[dict], list]:
    """The runs on ``backend``, each on a fresh database: the undisturbed one, then each kind of faults of
    ``--faults`` ``--repeat`` times; their rows, and the undisturbed run's certificates."""
    with fresh_database(backend) as url:
        t = time.perf_counter()
        status, line = undisturbed(args.n, url, args.workers)
        base_s = time.perf_counter() - t
        reference = inspect(url, args.n)
    expected = reference["certificates"]
    rows = [_row(backend, "none", 0, status, line, reference, base_s, 1.0)]
    injections = {
        "workers": ("workers killed", lambda u: kill_workers(args.n, u, args.workers, rng)),
        "coordinator": (
            "coordinator killed",
            lambda u: kill_coordinator(args.n, u, args.workers, rng, len(expected)),
        ),
    }
    kinds = [injections[k.strip()] for k in args.faults.split(",") if k.strip()]  # checked by run
    for name, inject in [k for k in kinds for _ in range(args.repeat)]:
        with fresh_database(backend) as url:
            t = time.perf_counter()
            injected, status, line = inject(url)
            seconds = time.perf_counter() - t
            seen = inspect(url, args.n)
        rows.append(_row(backend, name, injected, status, line, seen, seconds, round(seconds / base_s, 2)))
    return rows, expected


def _check(rows: list[dict], expected: list) -> bool:
    """Give each row the clusters ``expected`` and seen, and whether they are the same (its certificates
    dropped); whether every run ended well with them and nothing failed, left leased or pending, or duplicated."""
    ok = True
    for r in rows:
        r["expected"], r["seen"] = len(expected), len(r["certificates"])
        r["same_clusters"] = r.pop("certificates") == expected
        ok &= (
            r["exit"] == 0
            and r["same_clusters"]
            and not (r["failed"] or r["leased"] or r["pending"] or r["duplicates"])
        )
    return ok


def _print_table(args, rows: list[dict], early: dict) -> None:
    """The text of :func:`run`: a line per run, the runs that stopped early of each kind, and why each stopped."""
    cols = [
        "backend",
        "faults",
        "injected",
        "exit",
        "expected",
        "seen",
        "same_clusters",
        "pending",
        "failed",
        "leased",
        "duplicates",
        "retries",
        "isolated_failures",
        "seconds",
        "time_ratio",
    ]
    print(f"soak, n = {args.n}, {args.workers} workers, seed {args.seed}, allowed-failures {args.allowed_failures}")
    width = {c: max(len(c), *(len(str(r[c])) for r in rows)) for c in cols}
    print("  ".join(c.rjust(width[c]) for c in cols))
    for r in rows:
        print("  ".join(str(r[c]).rjust(width[c]) for c in cols))
    print("stopped early: " + "; ".join(f"{k} {e} of {t}" for k, (e, t) in early.items()))
    for r in rows:  # why a run that did not end well stopped: its last line on standard error
        if r["stopped"]:
            print(f"{r['backend']}, {r['faults']}: exit {r['exit']}: {r['stopped']}")
