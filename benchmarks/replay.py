"""The coordinator's and the database's ceiling: a run replayed with recorded expansions (docs/scaling.md).

Records, once, what ``packings.workers.expand`` returned for every cluster of a complete run (from its
database: the ``transitions`` rows and their targets' coordinates) into a file next to it; then, for each
number of writers K, drives a new run of n through the real coordinator (``packings.enumerate`` on a local
Dask cluster of K single-threaded worker processes: claims and leases, ``load_tasks``,
``record_expansions``) in a fresh database, the workers answering each expansion at once with its recorded
result, so that the coordinator, Dask and the database are the whole cost.  At the end the replay's
catalogue must equal the recorded one exactly (keys, geometries within 1e-7, counts by contacts, the
attempts of each cluster), with nothing pending, leased or failed: else the exit status is 1.

    python -m benchmarks replay --n 12 --source sqlite:///n12.db --db sqlite:///replay.db --writers 1 2 4

Each K gets its own fresh database, removed afterwards unless ``--keep``: with one K, ``--db`` itself
(created; it must hold no run of n yet), with several, ``--db`` with ``_kK`` appended to the file's stem or
the PostgreSQL database's name (a PostgreSQL database is created on its server if absent).
"""

from __future__ import annotations

import json
import os
import pickle
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from distributed import WorkerPlugin

TOLERANCE = 1e-7  #: how far a replayed geometry may be from the recorded one (after alignment)
FORMAT = 1  #: the recording file's format


def add_arguments(p) -> None:
    p.add_argument("--n", type=int, required=True, help="the number of spheres of the recorded run")
    p.add_argument("--db", required=True, help="database URL of the replay (see above)")
    p.add_argument("--writers", type=int, nargs="+", default=[2], metavar="K", help="worker processes (default 2)")
    p.add_argument("--source", default=None, help="database URL holding a complete run of n, to record")
    p.add_argument(
        "--recording",
        default=None,
        metavar="FILE",
        help="the recording (default: beside the --source SQLite file); made from --source if absent",
    )
    p.add_argument("--keep", action="store_true", help="keep the replay databases")
    p.add_argument(
        "--profile",
        default=None,
        metavar="DIR",
        help="write cProfile statistics of the coordinator and of each worker's task thread into DIR",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


# --------------------------------------------------------------------------- the recording


@dataclass
class Recording:
    """A complete run's expansions.  Clusters are numbered 0, 1, ... (``keys``, ``coords``, ...); ``sources``
    holds, for each cluster the run expanded, its attempts, pickled (unpickled only when replayed): a list
    of (broken, direction, outcome, steps, new contacts, target number or -1, target labels or None), the
    pairs as tuples, in the recorded cluster's labels."""

    n: int
    params: str  #: the run's parameters, as runs.params holds them
    keys: list[tuple[str, int]]  #: (certificate, embedding)
    coords: list[bytes]
    contact_lists: list[str]
    rigidity: list[tuple]  #: (kind, method, margin, flexes, stresses, singular)
    seed: int
    sources: dict[int, bytes] = field(default_factory=dict)
    left_out: int = 0  #: clusters of the run that no recorded path reaches from the seed (a catalysis pass's)

    def attempts(self, i: int) -> list[tuple]:
        return pickle.loads(self.sources[i])

    def reachable(self) -> list[int]:
        """The clusters reached from the seed by the recorded attempts: the replay's catalogue."""
        seen, todo = {self.seed}, [self.seed]
        while todo:
            for a in self.attempts(todo.pop()):
                t = a[5]
                if t >= 0 and t not in seen and t in self.sources:
                    seen.add(t)
                    todo.append(t)
        return sorted(seen)


def default_recording(source: str | None, n: int) -> Path | None:
    from packings.service.db import parse_url

    if source is None:
        return None
    u = parse_url(source)
    if u.get_backend_name() != "sqlite" or not u.database:
        return None
    return Path(u.database).with_name(f"{Path(u.database).name}.replay-n{n}.pickle")


def _pairs(pairs) -> tuple:
    from packings.workers.cluster import pair

    return tuple(pair(int(i), int(j)) for i, j in pairs)


def record(source: str, n: int, path: Path) -> Recording:
    """Read the complete run of n (default parameters) in ``source`` into ``path``."""
    from sqlalchemy import select

    from packings.service.db import open_database
    from packings.service.models import COMPLETE, ClusterRow, ExpansionRow, Run
    from packings.service.queries import transitions
    from packings.workers.params import Params

    engine = open_database(source)
    params = Params().to_json()
    try:
        with engine.connect() as c:
            run = c.execute(select(Run.id, Run.status).where(Run.n == n, Run.params == params)).one_or_none()
            if run is None or run.status != COMPLETE:
                raise SystemExit(f"replay: error: {source} holds no complete run of n = {n} with default parameters")
            rows = c.execute(
                select(
                    ClusterRow.id,
                    ClusterRow.certificate,
                    ClusterRow.embedding,
                    ClusterRow.coords,
                    ClusterRow.contact_list,
                    ClusterRow.rigid_kind,
                    ClusterRow.rigid_method,
                    ClusterRow.margin,
                    ClusterRow.flexes,
                    ClusterRow.stresses,
                    ClusterRow.singular,
                    ClusterRow.found_by,
                )
                .join(ExpansionRow, ExpansionRow.cluster_id == ClusterRow.id)
                .where(ExpansionRow.run_id == run.id)
                .order_by(ClusterRow.id)
            ).all()
            number = {r.id: k for k, r in enumerate(rows)}
            attempts: dict[int, list] = {k: [] for k in range(len(rows))}
            for t in transitions(c, run=run.id):
                attempts[number[t.source_id]].append(
                    (
                        _pairs(t.broken),
                        t.direction,
                        t.outcome,
                        t.steps,
                        _pairs(t.new_contacts),
                        -1 if t.target_id is None else number[t.target_id],
                        t.labels,
                    )
                )
    finally:
        engine.dispose()
    seeds = [k for k, r in enumerate(rows) if r.found_by == "seed"]
    if len(seeds) != 1:
        raise SystemExit(f"replay: error: the run of n = {n} in {source} has {len(seeds)} seeds, not one")
    rec = Recording(
        n,
        params,
        [(r.certificate, r.embedding) for r in rows],
        [bytes(r.coords) for r in rows],
        [r.contact_list for r in rows],
        [(r.rigid_kind, r.rigid_method, r.margin, r.flexes, r.stresses, r.singular) for r in rows],
        seeds[0],
        {k: pickle.dumps(a, protocol=pickle.HIGHEST_PROTOCOL) for k, a in attempts.items()},
    )
    reached = set(rec.reachable())
    rec.left_out = len(rows) - len(reached)
    rec.sources = {k: v for k, v in rec.sources.items() if k in reached}
    save(rec, path)
    return rec


def save(rec: Recording, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        pickle.dump((FORMAT, rec), f, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, path)


def load(path: Path) -> Recording:
    with open(path, "rb") as f:
        fmt, rec = pickle.load(f)
    if fmt != FORMAT:
        raise SystemExit(f"replay: error: {path} is a recording of another format; remove it to record again")
    return rec


# --------------------------------------------------------------------------- the replaying worker


class Replayer:
    """In a worker process: the recorded :class:`packings.workers.expand.Expansion` of a cluster as the
    replay's database stores it, in the place of ``expand`` (:meth:`expand`, which the worker plugin puts
    where :mod:`packings.service.tasks` calls it).

    The replay's clusters have other ids, and a cluster may be stored in other labels than in the
    recorded run (its first finder may differ).  So the recorded cluster is found by its certificate
    and geometry, and its attempts relabelled onto the replay's cluster: the broken and formed contacts,
    and each rigid endpoint given as its recorded target's coordinates in the source's labels where the
    recorded labels say them (else in the target's), with the target's rigidity.  The write-back's
    geometric deduplication matches it whatever its labels.  An attempt whose contacts have an arrival
    in the replay's database (``arrivals``: the paths that came to this cluster, when it is first-order
    rigid) is retraced as ``expand`` retraces it (:attr:`packings.workers.expand.Endpoint.reached`)."""

    def __init__(self, rec: Recording):
        from packings.workers.params import Params

        self.rec = rec
        self.tol_d = Params.from_dict(json.loads(rec.params)).tol_d
        self.by_cert: dict[str, list[int]] = {}
        for k in rec.sources:
            self.by_cert.setdefault(rec.keys[k][0], []).append(k)
        self._clusters: dict[int, object] = {}

    def cluster(self, k: int):
        from packings.service.models import core_cluster

        c = self._clusters.get(k)
        if c is None:
            c = self._clusters[k] = core_cluster(self.rec.n, self.rec.coords[k], self.rec.contact_lists[k])
        return c

    def expand(self, cluster, params, arrivals=()):
        from packings.workers.cluster import Cluster, pair
        from packings.workers.expand import RIGID, Endpoint, Expansion
        from packings.workers.expand import arrivals as by_contacts
        from packings.workers.identity import alignment, certificate_key, find_match
        from packings.workers.rigidity import Rigidity

        rec, n = self.rec, self.rec.n
        candidates = self.by_cert.get(certificate_key(cluster), [])
        k = find_match(cluster, [self.cluster(j) for j in candidates], self.tol_d)
        if k is None:
            raise LookupError("the replay reached a cluster the recording does not hold")
        src = candidates[k]
        recorded = self.cluster(src)
        p = None  # sphere i of the recorded cluster is sphere p[i] of the replay's
        if rec.coords[src] != np.ascontiguousarray(cluster.coords, dtype="<f8").tobytes():
            p = alignment(recorded, cluster, self.tol_d, same=True).tolist()

        def relabel(pairs):
            return pairs if p is None else tuple(sorted(pair(p[a], p[b]) for a, b in pairs))

        attempts = rec.attempts(src)
        kind, method, margin, flexes, stresses, singular = rec.rigidity[src]
        first_order_rigid = flexes == 0
        retrace = by_contacts(arrivals) if first_order_rigid and arrivals else {}
        directions = Counter(a[0] for a in attempts)
        endpoints, same_as, first = [], [], {}
        for broken, direction, outcome, steps, new, target, labels in attempts:
            b = relabel(broken)
            if outcome != RIGID or target < 0:
                endpoints.append(Endpoint(b, direction, outcome, None, steps, new_contacts=relabel(new)))
                same_as.append(None)
                continue
            a = retrace.get(b) if directions[broken] == 1 else None
            if a is not None:  # as expand retraces it: no cluster, the arrival's target
                endpoints.append(Endpoint(b, direction, RIGID, 1, a.steps, new_contacts=a.formed, reached=a))
                same_as.append(None)
                continue
            t = self.cluster(target)
            if labels is None:
                c = Cluster(t.coords, t.contacts)
            else:
                q = list(labels) if p is None else [0] * n  # sphere j of the endpoint is sphere q[j] of the target
                if p is not None:
                    for i, ti in enumerate(labels):
                        q[p[i]] = ti
                back = [0] * n
                for j, tj in enumerate(q):
                    back[tj] = j
                c = Cluster(t.coords[q], tuple(sorted(pair(back[a], back[b]) for a, b in t.contacts)))
            tk, tm, tmargin, tf, ts, _ = rec.rigidity[target]
            rig = Rigidity(True, tk, tf, ts, tm, tmargin)
            same_as.append(first.setdefault(target, len(endpoints)))
            endpoints.append(Endpoint(b, direction, RIGID, 1, steps, c, rig, relabel(new)))
        return Expansion(cluster, tuple(endpoints), tuple(same_as), first_order_rigid)


class ReplayPlugin(WorkerPlugin):
    """Loads the recording at ``path`` in each worker process and makes :mod:`packings.service.tasks`
    call :meth:`Replayer.expand` instead of ``expand``."""

    name = "packings-replay"

    def __init__(self, path: str, profile: str | None = None):
        self.path, self.profile = path, profile
        self.profiler = None

    def setup(self, worker) -> None:
        import packings.service.tasks as tasks

        tasks.expand = Replayer(load(Path(self.path))).expand
        time_write_lock()
        if self.profile:  # the worker's thread that runs the tasks: cProfile of the event loop's would miss them
            import cProfile

            self.profiler = cProfile.Profile()
            worker.executor.submit(self.profiler.enable).result()

    def teardown(self, worker) -> None:
        if self.profiler is not None:
            worker.executor.submit(self.profiler.disable).result()
            self.profiler.dump_stats(str(Path(self.profile) / f"worker-{os.getpid()}.prof"))


#: seconds this process held SQLite's write lock: from BEGIN IMMEDIATE to the end of the transaction
WRITE_LOCK = [0.0]


def time_write_lock() -> None:
    """Count in :data:`WRITE_LOCK` the time this process's SQLite transactions that write hold the write lock
    (each begins IMMEDIATE: :func:`packings.service.db._begin_immediate`); once per process."""
    from sqlalchemy import Engine, event

    import packings.service.db as db

    if getattr(db._begin_immediate, "timed", False):
        return
    real = db._begin_immediate

    def timed(conn) -> None:
        real(conn)
        conn.info["replay_locked_at"] = time.perf_counter()

    timed.timed = True
    db._begin_immediate = timed

    def ended(conn) -> None:
        t0 = conn.info.pop("replay_locked_at", None)
        if t0 is not None:
            WRITE_LOCK[0] += time.perf_counter() - t0

    event.listen(Engine, "commit", ended)
    event.listen(Engine, "rollback", ended)


def write_lock_seconds() -> float:
    return WRITE_LOCK[0]


# --------------------------------------------------------------------------- the check


def check(rec: Recording, url: str) -> list[str]:
    """What differs between the run of n in the database at ``url`` and the recording (empty: nothing):
    its status and frontier, the keys of its clusters, their geometries (within :data:`TOLERANCE`), the
    counts by contacts, and the number of attempts recorded for each cluster."""
    from sqlalchemy import func, select

    from packings.service import queries
    from packings.service.db import make_engine
    from packings.service.models import COMPLETE, DONE, AttemptsRow, ClusterRow, ExpansionRow, Run, core_cluster
    from packings.workers.identity import same_geometry

    problems = []
    engine = make_engine(url)
    try:
        with engine.connect() as c:
            run = c.execute(select(Run.id, Run.status).where(Run.n == rec.n, Run.params == rec.params)).one_or_none()
            if run is None:
                return [f"no run of n = {rec.n}"]
            if run.status != COMPLETE:
                problems.append(f"the run is {run.status}")
            frontier = queries.frontier(c, run.id)
            left = {k: v for k, v in frontier.items() if k != DONE and v}
            if left:
                problems.append(f"expansions not done: {left}")
            got = {
                (r.certificate, r.embedding): r
                for r in c.execute(
                    select(
                        ClusterRow.id,
                        ClusterRow.certificate,
                        ClusterRow.embedding,
                        ClusterRow.coords,
                        ClusterRow.contact_list,
                        ClusterRow.contacts,
                    )
                    .join(ExpansionRow, ExpansionRow.cluster_id == ClusterRow.id)
                    .where(ExpansionRow.run_id == run.id)
                )
            }
            attempts = dict(
                c.execute(
                    select(AttemptsRow.source_id, func.sum(AttemptsRow.attempts))
                    .where(AttemptsRow.run_id == run.id)
                    .group_by(AttemptsRow.source_id)
                ).all()
            )
    finally:
        engine.dispose()
    reach = rec.reachable()
    want = {rec.keys[k]: k for k in reach}
    missing, extra = want.keys() - got.keys(), got.keys() - want.keys()
    if missing:
        problems.append(f"{len(missing)} recorded cluster(s) missing, e.g. {sorted(missing)[0]}")
    if extra:
        problems.append(f"{len(extra)} cluster(s) not recorded (or keyed otherwise), e.g. {sorted(extra)[0]}")
    counts_want = Counter(sum(1 for _ in json.loads(rec.contact_lists[k])) for k in reach)
    counts_got = Counter(r.contacts for r in got.values())
    if counts_want != counts_got:
        problems.append(
            f"counts by contacts differ: recorded {dict(sorted(counts_want.items()))}, "
            f"replayed {dict(sorted(counts_got.items()))}"
        )
    far = attempts_off = 0
    for key in want.keys() & got.keys():
        k, r = want[key], got[key]
        a = core_cluster(rec.n, rec.coords[k], rec.contact_lists[k])
        b = core_cluster(rec.n, bytes(r.coords), r.contact_list)
        if not same_geometry(a, b, TOLERANCE):
            far += 1
        if attempts.get(r.id, 0) != len(rec.attempts(k)):
            attempts_off += 1
    if far:
        problems.append(f"{far} cluster(s) with another geometry than recorded (beyond {TOLERANCE:g})")
    if attempts_off:
        problems.append(f"{attempts_off} cluster(s) with another number of attempts than recorded")
    return problems


# --------------------------------------------------------------------------- databases


def _database_for(url: str, k: int, several: bool) -> str:
    from packings.service.db import parse_url

    u = parse_url(url)
    if not several:
        return url
    if u.get_backend_name() == "sqlite":
        path = Path(u.database)
        return u.set(database=str(path.with_name(f"{path.stem}_k{k}{path.suffix}"))).render_as_string(False)
    return u.set(database=f"{u.database}_k{k}").render_as_string(False)


def _create(url: str) -> None:
    """Make the replay's database, which must hold no run yet (PostgreSQL: created on its server if absent)."""
    from sqlalchemy import create_engine, text

    from packings.service.db import parse_url

    u = parse_url(url)
    if u.get_backend_name() == "sqlite":
        if not u.database or u.database == ":memory:":
            raise SystemExit("replay: error: the replay needs a SQLite file (its workers open it), not memory")
        if Path(u.database).exists():
            raise SystemExit(f"replay: error: {u.database} exists: the replay needs a fresh database")
        return
    admin = create_engine(u.set(database="postgres"), isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            if c.execute(text("SELECT 1 FROM pg_database WHERE datname = :d"), {"d": u.database}).first():
                raise SystemExit(f"replay: error: database {u.database} exists: the replay needs a fresh database")
            c.execute(text(f'CREATE DATABASE "{u.database}"'))
    finally:
        admin.dispose()


def _remove(url: str) -> None:
    from sqlalchemy import create_engine, text

    from packings.service.db import parse_url

    u = parse_url(url)
    if u.get_backend_name() == "sqlite":
        for suffix in ("", "-wal", "-shm", "-journal"):
            Path(u.database + suffix).unlink(missing_ok=True)
        return
    admin = create_engine(u.set(database="postgres"), isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{u.database}" WITH (FORCE)'))
    finally:
        admin.dispose()


# --------------------------------------------------------------------------- the replay


def replay(rec: Recording, path: Path, url: str, writers: int, profile: str | None = None) -> dict:
    """One replay of ``rec`` (saved at ``path``) into the fresh database ``url`` on ``writers`` workers."""
    from sqlalchemy import func, select

    import packings
    from packings.service.dask_cluster import dask_client
    from packings.service.db import make_engine
    from packings.service.models import ExpansionRow

    plugin = ReplayPlugin(str(path), profile and str(Path(profile) / f"k{writers}"))
    if profile:
        Path(plugin.profile).mkdir(parents=True, exist_ok=True)
    with dask_client(None, writers, True, plugins=(plugin,), dashboard_address=":0") as dask:
        workers = list(dask.client.run(os.getpid).values())
        time_write_lock()  # the coordinator's claims hold it too
        locked = WRITE_LOCK[0] + sum(dask.client.run(write_lock_seconds).values())
        before = _cpu(workers), _cpu(_servers(url)), time.process_time()
        t0 = time.perf_counter()
        profiler = None
        if profile:
            import cProfile

            profiler = cProfile.Profile()
            profiler.enable()
        with _Resident() as rss:
            result = packings.enumerate(rec.n, url, scheduler=dask.cluster, progress=False, glued=False)
        if profiler is not None:
            profiler.disable()
            profiler.dump_stats(str(Path(plugin.profile) / "coordinator.prof"))
        wall = time.perf_counter() - t0
        locked = WRITE_LOCK[0] + sum(dask.client.run(write_lock_seconds).values()) - locked
        cpu = {
            "coordinator": time.process_time() - before[2],
            "workers": _cpu(workers) - before[0],
            "database": _cpu(_servers(url)) - before[1],
        }
    problems = check(rec, url)
    engine = make_engine(url)
    try:
        with engine.connect() as c:
            in_expand = c.execute(
                select(func.coalesce(func.sum(ExpansionRow.seconds), 0.0)).where(ExpansionRow.run_id == result.run_id)
            ).scalar_one()
    finally:
        engine.dispose()
    done = result.diagnostics.get("expansions", 0)
    return {
        "backend": engine.dialect.name,
        "writers": writers,
        "expansions": done,
        "clusters": result.total,
        "run_s": round(result.seconds, 3),
        "wall_s": round(wall, 3),
        "rate": round(done / result.seconds, 1) if result.seconds else None,
        "in_replayed_expand_s": round(float(in_expand), 3),
        # CPU seconds per expansion: the coordinator's process (its Dask scheduler's thread too), the workers'
        # (the write-backs, and the replayed expand), the database server's processes (PostgreSQL on this host)
        **{f"cpu_ms_{k}": round(1000 * v / done, 3) if done else None for k, v in cpu.items()},
        # SQLite: ms its write lock was held per expansion (by the write-backs and the claims): the serial part
        "write_lock_ms": round(1000 * locked / done, 3) if done and engine.dialect.name == "sqlite" else None,
        # resident MiB of the coordinator's process, its Dask scheduler in it: as the run started, a quarter
        # into it, at its largest, as it ended (what it keeps of the tasks done shows as growth after the quarter)
        **rss.mib,
        "problems": problems,
    }


class _Resident:
    """Samples this process's resident memory every ``every`` seconds while in the block: ``mib`` gives
    the first sample, the one a quarter of the way, the largest and the last (MiB)."""

    def __init__(self, every: float = 0.5):
        import threading

        self.every, self.samples, self.stop = every, [], threading.Event()
        self.thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self) -> None:
        import psutil

        me = psutil.Process()
        while True:
            self.samples.append(me.memory_info().rss / 2**20)
            if self.stop.wait(self.every):
                self.samples.append(me.memory_info().rss / 2**20)
                return

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join()

    @property
    def mib(self) -> dict:
        s = self.samples
        return {
            "rss_start_mib": round(s[0], 1),
            "rss_quarter_mib": round(s[len(s) // 4], 1),  # a quarter into the run: its caches warm
            "rss_peak_mib": round(max(s), 1),
            "rss_end_mib": round(s[-1], 1),
        }


def _cpu(pids) -> float:
    """CPU seconds (user and system) of the processes ``pids`` that are still there."""
    import psutil

    total = 0.0
    for pid in pids:
        try:
            t = psutil.Process(pid).cpu_times()
        except psutil.Error:
            continue
        total += t.user + t.system
    return total


def _servers(url: str) -> list[int]:
    """The processes of a PostgreSQL server on this host (all of them: other databases' backends too), none for SQLite."""
    import psutil

    from packings.service.db import parse_url

    if parse_url(url).get_backend_name() == "sqlite":
        return []
    return [p.pid for p in psutil.process_iter(["name"]) if p.info["name"] in ("postgres", "postmaster")]


def run(args) -> int:
    from packings.service.errors import PackingsError

    path = Path(args.recording) if args.recording else default_recording(args.source, args.n)
    if path is None:
        print("replay: error: give --recording FILE (or a SQLite --source to record beside)", file=sys.stderr)
        return 2
    try:
        if path.exists():
            rec = load(path)
        elif args.source is None:
            print(f"replay: error: {path} does not exist: give --source to record it", file=sys.stderr)
            return 2
        else:
            t0 = time.perf_counter()
            rec = record(args.source, args.n, path)
            print(
                f"replay: recorded {len(rec.sources)} expansions in {time.perf_counter() - t0:.1f} s into {path}",
                file=sys.stderr,
            )
        if rec.n != args.n:
            print(f"replay: error: {path} records n = {rec.n}, not {args.n}", file=sys.stderr)
            return 2
        rows = []
        several = len(args.writers) > 1
        for k in args.writers:
            url = _database_for(args.db, k, several)
            _create(url)
            try:
                rows.append(replay(rec, path, url, k, args.profile))
            finally:
                if not args.keep:
                    _remove(url)
    except PackingsError as e:
        print(f"replay: error: {e}", file=sys.stderr)
        return 2
    report = {"n": rec.n, "recorded": len(rec.sources), "left_out": rec.left_out, "rows": rows}
    if args.json:
        print(json.dumps(report))
    else:
        print(
            f"n = {rec.n}: {len(rec.sources)} recorded expansions"
            + (f" ({rec.left_out} clusters no recorded path reaches left out)" if rec.left_out else "")
        )
        print("CPU ms per expansion: of the coordinator (with its scheduler), the workers, the database server;")
        print("lock: ms SQLite's write lock was held per expansion (its write-backs and claims);")
        print(
            "MiB: the coordinator's process (its scheduler in it) resident at the run's start, a quarter in, most, end"
        )
        print(
            f"{'backend':<11}{'K':>4}{'expansions':>11}{'run s':>8}{'exp/s':>8}{'coord':>7}{'workers':>8}{'db':>6}"
            f"{'lock':>6}{'MiB start/¼/peak/end':>22}  check"
        )
        for r in rows:
            print(
                f"{r['backend']:<11}{r['writers']:>4}{r['expansions']:>11}{r['run_s']:>8.2f}{r['rate']:>8.1f}"
                f"{r['cpu_ms_coordinator']:>7.2f}{r['cpu_ms_workers']:>8.2f}{r['cpu_ms_database']:>6.2f}"
                f"{r['write_lock_ms'] or 0:>6.2f}"
                f"{r['rss_start_mib']:>6.0f}/{r['rss_quarter_mib']:.0f}/{r['rss_peak_mib']:.0f}/{r['rss_end_mib']:.0f}  "
                f"{'; '.join(r['problems']) or 'equal'}"
            )
    return 1 if any(r["problems"] for r in rows) else 0
