"""What several test files use: test clusters and their copies, the enumerations the tests compare with,
the command line run as a user runs it, waits that poll against a deadline, and filled databases.

Test files import from here, never from one another.  Heavy imports (SQLAlchemy, the service) are made
inside the functions that need them, so that the numerical tests load none of them.
"""

from __future__ import annotations

import functools
import json
import os
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import settings
from hypothesis import strategies as st

from packings.workers.cluster import Cluster
from packings.workers.params import DEFAULT

DATA = Path(__file__).parent / "data"
ROOT = Path(__file__).resolve().parent.parent

# --------------------------------------------------------------------------- test clusters

TOL_D = DEFAULT.tol_d
H_TET = np.sqrt(2.0 / 3.0)  # height of a unit tetrahedron above a face

SETTINGS = settings(derandomize=True, max_examples=25, deadline=None, database=None)


def glue(x: np.ndarray, face: tuple[int, int, int], side: float) -> np.ndarray:
    """Centre of a sphere touching the three spheres of ``face`` (side = +-1)."""
    a, b, c = x[list(face)]
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal)
    return (a + b + c) / 3.0 + side * H_TET * normal


def glue_away(x: np.ndarray, face: tuple[int, int, int], away: int) -> np.ndarray:
    """The gluing position on the side of ``face`` away from sphere ``away``."""
    p, q = glue(x, face, 1.0), glue(x, face, -1.0)
    return p if np.linalg.norm(p - x[away]) > np.linalg.norm(q - x[away]) else q


def tetrahedron_coords() -> np.ndarray:
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, np.sqrt(3.0) / 2.0, 0.0]])
    return np.vstack([x, glue(x, (0, 1, 2), 1.0)])


def tetrahedron() -> Cluster:
    return Cluster.from_coords(tetrahedron_coords())


def octahedron() -> Cluster:
    e = np.eye(3) / np.sqrt(2.0)
    return Cluster.from_coords(np.vstack([e, -e]))


def bipyramid() -> Cluster:
    x = tetrahedron_coords()
    return Cluster.from_coords(np.vstack([x, glue_away(x, (0, 1, 2), 3)]))


def polytetrahedron() -> Cluster:
    """Three tetrahedra sharing the edge 0-1 (n = 6, 12 contacts)."""
    x = tetrahedron_coords()
    x = np.vstack([x, glue_away(x, (0, 1, 2), 3)])  # sphere 4
    x = np.vstack([x, glue_away(x, (0, 1, 4), 2)])  # sphere 5
    return Cluster.from_coords(x)


def random_glued(n: int, seed: int) -> Cluster:
    """Glue spheres onto random faces (triangles of touching spheres) of a
    tetrahedron until there are n, rejecting overlaps and near-contacts."""
    rng = np.random.default_rng(seed)
    x = tetrahedron_coords()
    while len(x) < n:
        c = Cluster.from_coords(x)
        adj = c.adjacency()
        faces = [
            (i, j, k)
            for i in range(len(x))
            for j in range(i + 1, len(x))
            for k in range(j + 1, len(x))
            if adj[i, j] and adj[i, k] and adj[j, k]
        ]
        face = faces[rng.integers(len(faces))]
        p = glue(x, face, rng.choice([-1.0, 1.0]))
        d = np.linalg.norm(x - p, axis=1)
        if np.any(d < 1.0 - 1e-9) or np.any((d > 1.0 + 1e-9) & (d < 1.0 + 1e-3)):
            continue
        x = np.vstack([x, p])
    return Cluster.from_coords(x)


def chain(dihedral_deg: float, angle_deg: float = 120.0) -> Cluster:
    """4-sphere chain 0-1-2-3 with unit bonds, bond angles ``angle_deg`` and
    dihedral angle ``dihedral_deg``; contacts given explicitly."""
    th, ph = np.radians(angle_deg), np.radians(dihedral_deg)
    p0 = np.array([0.0, 0.0, 0.0])
    p1 = np.array([1.0, 0.0, 0.0])
    p2 = p1 + np.array([-np.cos(th), np.sin(th), 0.0])
    bc = (p2 - p1) / np.linalg.norm(p2 - p1)
    nrm = np.cross(p1 - p0, bc)
    nrm /= np.linalg.norm(nrm)
    m = np.cross(nrm, bc)
    p3 = p2 + (-np.cos(th)) * bc + np.sin(th) * np.cos(ph) * m + np.sin(th) * np.sin(ph) * nrm
    return Cluster(np.array([p0, p1, p2, p3]), ((0, 1), (1, 2), (2, 3)))


#: five geometries of the 4-chain's one contact graph, the most compact first (embedding order)
CHAIN_DIHEDRALS = (0.0, 45.0, 90.0, 135.0, 180.0)

CLUSTERS = {
    "tetrahedron": tetrahedron(),
    "bipyramid": bipyramid(),
    "octahedron": octahedron(),
    "polytetrahedron": polytetrahedron(),
    "glued8": random_glued(8, 3),
    "glued9": random_glued(9, 5),
    "glued10": random_glued(10, 11),
    "chain60": chain(60.0),
}

names = st.sampled_from(sorted(CLUSTERS))
seeds = st.integers(0, 2**32 - 1)


def near_misses() -> list[dict]:
    """The two n = 12 path endpoints stored as clusters before packings.workers.paths._endpoint re-projected
    (tests/data/n12_near_miss.json), as Clusters with their record."""
    data = json.loads((DATA / "n12_near_miss.json").read_text())
    return [
        {**m, "cluster": Cluster(np.array(m["coords"]), tuple(map(tuple, m["contacts"])))} for m in data["endpoints"]
    ]


def two_geometries() -> tuple[Cluster, Cluster]:
    """The two geometries of one n = 11 contact graph (tests/data/n11_two_geometries.json)."""
    data = json.loads((DATA / "n11_two_geometries.json").read_text())
    a, b = (Cluster(np.array(c["coords"]), tuple(map(tuple, c["contacts"]))) for c in data["clusters"])
    return a, b


# --------------------------------------------------------------------------- congruent copies


def random_orthogonal(rng: np.random.Generator, reflect: bool) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if (np.linalg.det(q) < 0) != reflect:
        q[:, 0] = -q[:, 0]
    return q


def relabel(cluster: Cluster, perm: np.ndarray, coords: np.ndarray | None = None) -> Cluster:
    """New sphere k is old sphere perm[k]; contacts mapped explicitly."""
    inv = np.argsort(perm)
    x = cluster.coords if coords is None else coords
    return Cluster(x[perm], tuple((int(inv[i]), int(inv[j])) for i, j in cluster.contacts))


def transformed(cluster: Cluster, seed: int, reflect: bool, noise: float = 0.0) -> Cluster:
    """Rotated (improperly if ``reflect``), translated, relabelled, optionally noisy copy."""
    rng = np.random.default_rng(seed)
    q = random_orthogonal(rng, reflect)
    t = rng.uniform(-5.0, 5.0, size=3)
    x = cluster.coords @ q.T + t + rng.uniform(-noise, noise, size=cluster.coords.shape)
    return relabel(cluster, rng.permutation(cluster.n), x)


def congruent_copy(c: Cluster, rng: np.random.Generator | int, reflect: bool) -> tuple[Cluster, np.ndarray]:
    """``c`` rotated (reflected too if asked), translated and relabelled at random; and ``inv``: sphere i of
    ``c`` is sphere ``inv[i]`` of the copy.  ``rng`` is a generator or a seed for one."""
    rng = np.random.default_rng(rng)
    q = random_orthogonal(rng, reflect)
    perm = rng.permutation(c.n)
    return relabel(c, perm, c.coords @ q.T + rng.standard_normal(3)), np.argsort(perm)


# --------------------------------------------------------------------------- enumerations


@functools.lru_cache(maxsize=None)
def catalogue(n: int):
    """The in-memory enumeration of n with the default parameters (packings.workers.explore), computed
    once per test session: n = 9 takes seconds and n = 10 half a minute, and many tests compare with them.
    Its clusters are immutable; a test must not add to its index."""
    from packings.workers.explore import explore

    return explore(n)


# --------------------------------------------------------------------------- the command line


def packings(*args: str, cwd=None, env=None, timeout: float = 1800) -> subprocess.CompletedProcess:
    """``packings ARGS`` in a new process, as a user runs it (this Python's installed package)."""
    return subprocess.run(
        [sys.executable, "-m", "packings.service.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd,
        env=env,
    )


def start(*args: str) -> subprocess.Popen:
    """``packings ARGS`` started in the background, its output read through pipes."""
    return subprocess.Popen(
        [sys.executable, "-m", "packings.service.cli", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def run_many(*commands, cwd=None) -> list[subprocess.CompletedProcess]:
    """Several commands at once (each a list of arguments), their results in order."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=8) as pool:
        return list(pool.map(lambda args: packings(*args, cwd=cwd), commands))


def ok(*args: str, cwd=None) -> str:
    """The standard output of ``packings ARGS``, which must succeed."""
    r = packings(*args, cwd=cwd)
    assert r.returncode == 0, r.stderr
    return r.stdout


def one_line_error(r: subprocess.CompletedProcess, *words: str) -> str:
    """``r`` failed as a user's mistake must: a non-zero exit, nothing on standard output, one line
    ``packings: error: ...`` holding ``words`` on standard error and no traceback; returns that line."""
    assert r.returncode != 0, r.args
    assert "Traceback" not in r.stderr, r.stderr
    assert r.stdout == "", (r.args, r.stdout)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("packings: error:"), (r.args, r.stderr)
    assert all(w in lines[0] for w in words), (r.args, lines[0])
    return lines[0]


# --------------------------------------------------------------------------- waiting and processes


#: Dask's scheduler gives a task lost with its worker to another one up to allowed-failures (3) times
#: before it raises KilledWorker; at 0 every task a kill finds on its worker (running or queued there)
#: reaches the coordinator, so that each kill of a busy worker is a fault the coordinator must absorb,
#: whatever the timing (at 1 only a task hit twice does, which a fast run may never see).  A task of
#: several expansions lost so is put back; one alone is charged an attempt, which the tests below
#: keep out of reach of max-attempts by stopping the kills once a task has been put back.
SURFACE_KILLS = {"DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "0"}


def wait_for(
    predicate: Callable[[], Any],
    proc: subprocess.Popen | None = None,
    timeout: float = 300.0,
    interval: float = 0.05,
    what: str = "",
    explain: Callable[[], str] | None = None,
) -> Any:
    """Poll ``predicate`` until it gives something true, and return that; fail once ``timeout`` seconds
    have passed.  With ``proc``, also fail at once if that process ends first (what is waited for will
    not come); on a timeout ``proc`` is stopped and what it wrote to stderr is in the failure, with
    ``explain()`` (the state of what was waited on) if given."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            err = proc.stderr.read() if proc.stderr else ""
            pytest.fail(f"the process ended (status {proc.returncode}) before {what or 'the wait ended'}: {err}")
        if time.monotonic() > deadline:
            state = f"; {explain()}" if explain is not None else ""
            pytest.fail(f"not within {timeout} s: {what or predicate}{state}{_stopped(proc)}")
        time.sleep(interval)


def _stopped(proc: subprocess.Popen | None) -> str:
    """Stop ``proc`` (SIGTERM, then SIGKILL) and return what it wrote to stderr, for a failure's message."""
    if proc is None:
        return ""
    proc.terminate()
    try:
        _, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    return f"; the process's stderr:\n{err}" if err else ""


def fetch(url: str, timeout: float = 10.0) -> tuple[int, str]:
    """(status, body) of a GET of ``url`` (a dashboard page)."""
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return r.status, r.read().decode()


def free_port() -> int:
    """A TCP port free on 127.0.0.1 just now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listening(port: int) -> bool:
    """Whether something accepts connections on 127.0.0.1:``port``."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=1):
            return True
    except OSError:
        return False


def wait_until_listening(port: int, timeout: float = 120.0) -> None:
    """A `dask scheduler` just launched takes seconds to listen (longer on a loaded machine)."""
    wait_for(lambda: listening(port), timeout=timeout, interval=0.2, what=f"something listens on port {port}")


def stop(procs: list) -> None:
    """Terminate processes, the last started first; kill those that do not end within 30 s."""
    for p in reversed(procs):
        p.terminate()
    for p in procs:
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()


# --------------------------------------------------------------------------- databases

#: an admin URL of the PostgreSQL server the PostgreSQL variants of the database tests use
PG_ADMIN = os.environ.get("PACKINGS_TEST_PG", "postgresql://postgres@127.0.0.1:5432/postgres")
_pg_problem: list[str] = []


def _pg_available() -> str | None:
    """None if PostgreSQL answers, else why not."""
    if not _pg_problem:
        try:
            from sqlalchemy import create_engine, text

            from packings.service.db import parse_url

            eng = create_engine(parse_url(PG_ADMIN), isolation_level="AUTOCOMMIT")
            with eng.connect() as c:
                c.execute(text("SELECT 1"))
            eng.dispose()
            _pg_problem.append("")
        except Exception as e:  # noqa: BLE001 - any failure means "no server here"
            _pg_problem.append(
                f"no PostgreSQL at {PG_ADMIN} ({str(e).splitlines()[0][:120]}); "
                "set PACKINGS_TEST_PG to an admin URL to run these tests"
            )
    return _pg_problem[0] or None


@contextmanager
def pg_database():
    """A fresh, empty PostgreSQL database (URL) at any scope, dropped on leaving;
    skips (or fails, under PACKINGS_REQUIRE_PG=1) without a server."""
    from benchmarks.soak import postgresql_database

    problem = _pg_available()
    if problem:
        if os.environ.get("PACKINGS_REQUIRE_PG") == "1":
            pytest.fail(problem)
        pytest.skip(problem)
    with postgresql_database(PG_ADMIN, "packings_test") as url:
        yield url


def fill_database(engine, n: int, params=None, owner: str = "test:0:inline") -> int:
    """Run the whole enumeration of n in this process (no Dask), through the
    same store functions the service uses; returns the run id."""
    from packings.service import store
    from packings.service.db import sessions
    from packings.service.tasks import run_expansion
    from packings.workers.params import Params

    Session_ = sessions(engine)
    info = store.start_run(Session_, n, params or Params(), owner)
    while True:
        batch = store.claim(Session_, info.id, owner, 8)
        if not batch:
            break
        for eid, token in batch:
            run_expansion(Session_, eid, token)
    store.finish_run(Session_, info.id, owner, 0.0)
    return info.id


@dataclass
class Catalog:
    engine: Any  #: sqlalchemy.Engine
    runs: dict[int, int]  #: n -> run id

    @property
    def url(self) -> str:
        return str(self.engine.url.render_as_string(hide_password=False))


def filled_catalog(*ns: int):
    """A module-scoped fixture: a :class:`Catalog` holding the enumerations of ``ns``, on SQLite and on
    PostgreSQL (as the ``engine`` fixture), filled once; ``catalog = filled_catalog(7, 8)`` in a test
    module whose tests only read it."""

    @pytest.fixture(scope="module", params=["sqlite", "postgresql"])
    def catalog(request, tmp_path_factory):
        from packings.service.db import open_database

        if request.param == "sqlite":
            database = nullcontext(f"sqlite:///{tmp_path_factory.mktemp('catalog') / 'packings.db'}")
        else:
            database = pg_database()
        with database as url:
            engine = open_database(url, create=True)
            try:
                yield Catalog(engine, {n: fill_database(engine, n) for n in ns})
            finally:
                engine.dispose()

    return catalog


def done_count(url: str) -> int:
    """How many expansions the database at ``url`` has done (0 while it has no schema)."""
    from sqlalchemy import func, select

    from packings.service.db import make_engine, sessions
    from packings.service.models import ExpansionRow

    engine = make_engine(url)
    try:
        with sessions(engine)() as s:
            return s.execute(
                select(func.count()).select_from(ExpansionRow).where(ExpansionRow.status == "done")
            ).scalar()
    except Exception:  # noqa: BLE001 - the schema may not exist yet
        return 0
    finally:
        engine.dispose()


def assert_same_clusters(url: str, n: int, reference) -> None:
    """The database holds exactly the reference clusters: one stored cluster per
    reference cluster (same certificate and geometry), no duplicates."""
    from sqlalchemy import func, select

    from packings.service.db import make_engine, sessions
    from packings.service.models import LEASED, PENDING, ClusterRow, ExpansionRow
    from packings.workers.identity import ClusterIndex
    from packings.workers.params import Params

    engine = make_engine(url)
    with sessions(engine)() as s:
        rows = s.execute(select(ClusterRow).where(ClusterRow.n == n)).scalars().all()
        stored = [r.to_core() for r in rows]
        keys = [(r.certificate, r.embedding) for r in rows]
        frontier = dict(s.execute(select(ExpansionRow.status, func.count()).group_by(ExpansionRow.status)).all())
    engine.dispose()
    assert len(set(keys)) == len(keys)
    assert frontier.get(LEASED, 0) == 0 and frontier.get(PENDING, 0) == 0
    index = ClusterIndex()
    for c in reference:
        index.add(c, Params().tol_d)
    matched = set()
    for c in stored:
        i, new = index.add(c, Params().tol_d)
        assert not new, "a stored cluster that the uninterrupted run does not have"
        matched.add(i)
    assert len(matched) == len(reference) == len(stored)


def store_chains(S, order, seed: int, one_transaction: bool = False) -> dict[int, int]:
    """Geometries ``order`` of the 4-chain (:data:`CHAIN_DIHEDRALS`), each moved, reflected and relabelled,
    stored in that order through the store's functions; their ids by geometry."""
    from packings.service import store
    from packings.workers.identity import certificate_key
    from packings.workers.params import Params
    from packings.workers.rigidity import Rigidity

    params, ids = Params(), {}
    floppy = Rigidity(False, "floppy", 1, 0, "first-order")  # the store does not test what it stores
    clusters = [(k, transformed(chain(CHAIN_DIHEDRALS[k]), seed + i, bool(i % 2))) for i, k in enumerate(order)]
    cert = certificate_key(clusters[0][1])

    def insert(s, k, c, rows) -> None:
        store.lock_certificates(s, [(4, cert)])
        ids[k], new = store.insert_or_match(s, c, floppy, None, params.tol_d, rows, found_by="seed", source_id=None)
        assert new

    if one_transaction:
        with S.begin() as s:
            rows = store.stored_with(s, 4, [cert])[cert]
            for k, c in clusters:
                insert(s, k, c, rows)
            assert [r.embedding for r in rows] == list(range(len(order)))
    else:
        for k, c in clusters:
            with S.begin() as s:
                insert(s, k, c, None)
    return ids


def embeddings(S, ids: dict[int, int]) -> dict[int, int]:
    """The embedding numbers of the stored clusters ``ids`` (geometry -> id), by geometry."""
    from sqlalchemy import bindparam, select

    from packings.service.models import ClusterRow

    with S() as s:  # the column alone: the schema may be an older revision's
        q = select(ClusterRow.embedding).where(ClusterRow.id == bindparam("cid"))
        return {k: s.execute(q, {"cid": cid}).scalar_one() for k, cid in ids.items()}
