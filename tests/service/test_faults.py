"""Fault injection: infrastructure faults are not attempts, and a run survives them on its own.

Two kinds of test.  In-process ones make a task fail the way a lost worker makes it fail (Dask's
``KilledWorker``), deterministically, and check what the coordinator does with its expansions.  Real
ones kill processes (Dask workers, the coordinator) at moments drawn from a seeded generator, on
both backends, and check that the run completes by itself with exactly the clusters of an
undisturbed run, nothing failed, nothing left leased, no duplicate, and each expansion's transitions
written once and whole.  The seed of a real test is in its name (``[seed]``): a failure reproduces
the same schedule of faults (what they hit still depends on the machine's timing).
"""

from __future__ import annotations

import json
import random
import signal
import subprocess
import time
from collections import Counter

import pytest
from sqlalchemy import func, select

from benchmarks.soak import worker_processes
from packings.service import queries
from packings.service.db import make_engine, sessions
from packings.service.models import DONE, FAILED, LEASED, ClusterRow, ExpansionRow, Run
from packings.workers.params import Params
from tests.helpers import (
    SURFACE_KILLS,
    assert_same_clusters,
    catalogue,
    done_count,
    free_port,
    start,
    stop,
    wait_for,
    wait_until_listening,
)
from tests.helpers import packings as cli


class _LostWorker:
    address = "tcp://127.0.0.1:0"


def _killed_worker(key: str):
    from distributed.scheduler import KilledWorker

    return KilledWorker(key, _LostWorker(), 0)


def _in_process_run(engine, n: int, monkeypatch, task, max_attempts: int = 3):
    """run_enumeration of n on a LocalCluster of threads, its tasks replaced by ``task(real, expansions,
    plugin)`` (threads of this process: the patch reaches them)."""
    from distributed import Client, LocalCluster

    import packings.service.coordinator
    from packings.service.coordinator import run_enumeration

    real = packings.service.coordinator.expand_task
    monkeypatch.setattr(packings.service.coordinator, "expand_task", lambda e, p: task(real, e, p))
    url = engine.url.render_as_string(hide_password=False)
    with (
        LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        return run_enumeration(engine, url, n, Params(), client, max_attempts=max_attempts)


def _expansions(engine) -> list[ExpansionRow]:
    with sessions(engine)() as s:
        rows = s.execute(select(ExpansionRow).order_by(ExpansionRow.id)).scalars().all()
        s.expunge_all()
    return rows


def test_a_lost_task_puts_its_expansions_back_without_using_an_attempt(engine, monkeypatch, paper_counts):
    """The first tasks of several expansions are lost as with a dead worker: their expansions go back
    to pending with no attempt used, each is then sent alone, and the run completes with max_attempts 1."""
    import packings.service.tasks

    batches, lost = [], set()
    # tasks are pickled, closures by value: they reach the lists through a module
    monkeypatch.setattr(packings.service.tasks, "fault_log", (batches, lost), raising=False)

    def task(real, expansions, plugin):
        batches, lost = packings.service.tasks.fault_log
        ids = [eid for eid, _ in expansions]
        batches.append(ids)
        if len(ids) > 1 and len(lost) < 3:
            lost.add(tuple(ids))
            raise _killed_worker(f"expand-{ids[0]}")
        return real(expansions, plugin)

    result = _in_process_run(engine, 9, monkeypatch, task, max_attempts=1)
    assert result.status == "complete" and result.errors == []
    assert result.by_contacts == {int(k): v for k, v in paper_counts["clusters_by_contacts"]["9"].items()}
    assert len(lost) == 3
    put_back = {eid for ids in lost for eid in ids}
    rows = _expansions(engine)
    assert all(e.status == DONE and e.attempts == 1 and e.isolated_failures == 0 for e in rows)
    assert {e.id for e in rows if e.retries} == put_back and all(e.retries == 1 for e in rows if e.id in put_back)
    # after its task was lost, each went out alone
    for eid in put_back:
        later = [ids for ids in batches if eid in ids][1:]
        assert later == [[eid]]


def test_an_expansion_that_kills_every_worker_alone_ends_failed(engine, monkeypatch):
    """An expansion whose task is lost every time: its first loss (in a batch or not) is a retry, each
    loss alone an attempt; after max_attempts it is failed, and nothing else is."""
    import packings.service.store
    import packings.service.tasks
    from packings.workers.identity import same_geometry

    poison = catalogue(8).clusters[4]
    monkeypatch.setattr(packings.service.tasks, "fault_log", (sessions(engine), poison, Params().tol_d), raising=False)

    def task(real, expansions, plugin):
        Session_, poison, tol_d = packings.service.tasks.fault_log  # tasks are pickled: reach them through a module
        loaded = packings.service.store.load_tasks(Session_, expansions)
        if any(same_geometry(t.cluster, poison, tol_d) for t in loaded.values()):
            raise _killed_worker(f"expand-{expansions[0][0]}")
        return real(expansions, plugin)

    result = _in_process_run(engine, 8, monkeypatch, task, max_attempts=2)
    assert result.status == "incomplete" and len(result.errors) == 1
    assert "lost its workers while running alone" in result.errors[0]
    rows = _expansions(engine)
    [bad] = [e for e in rows if e.status == FAILED]
    assert (bad.retries, bad.attempts, bad.isolated_failures) == (1, 2, 2)
    assert all(e.status == DONE and e.isolated_failures == 0 for e in rows if e.id != bad.id)
    r = cli("status", "--json", "--db", engine.url.render_as_string(hide_password=False))
    [run] = json.loads(r.stdout)
    assert (run["failed"], run["isolated_failures"]) == (1, 2) and run["retries"] >= 1


def _assert_transitions_whole(url: str, n: int) -> None:
    """Each done expansion's transitions were written once and whole: as many, with the same outcomes,
    as expanding its stored cluster again gives (deterministic for given coordinates)."""
    from packings.workers.expand import expand

    engine = make_engine(url)
    with sessions(engine)() as s:
        done = s.execute(
            select(ExpansionRow.cluster_id, ClusterRow)
            .join(ClusterRow, ClusterRow.id == ExpansionRow.cluster_id)
            .where(ExpansionRow.status == DONE, ClusterRow.n == n)
        ).all()
        every = list(queries.transitions(s))
        stored = Counter((t.source_id, t.outcome) for t in every)
        per_attempt = sum(k > 1 for k in Counter((t.source_id, t.broken, t.direction) for t in every).values())
        params = Params.from_dict(json.loads(s.execute(select(Run.params)).scalar_one()))
    engine.dispose()
    assert per_attempt == 0
    for cid, row in done:
        ex = expand(row.to_core(), params)
        want = Counter(e.outcome for e in ex.endpoints)
        got = Counter({o: k for (c, o), k in stored.items() if c == cid})
        assert got == want, f"cluster {cid}"


def _faults(url: str) -> dict:
    r = cli("status", "--json", "--db", url)
    [run] = json.loads(r.stdout)
    return run


def _retries(url: str) -> int:
    """How many times the run's expansions have been put back after a lost task, so far."""
    engine = make_engine(url)
    try:
        with sessions(engine)() as s:
            return s.execute(select(func.coalesce(func.sum(ExpansionRow.retries), 0))).scalar()
    finally:
        engine.dispose()


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1])
def test_workers_killed_at_random_the_run_completes_by_itself(db_url, reference10, seed, monkeypatch):
    """Kill one of two worker processes every 0.15-0.6 s (seeded) during an n = 10 run, each lost task
    reaching the coordinator as KilledWorker, until at least three kills are done and a task has been
    put back: the run completes by itself, exact, its expansions put back rather than failed.  (At 1-3 s
    a quiet machine's n = 10 run could end after two kills, and on a fast one at 0.3-1 s.)"""
    rng = random.Random(seed)
    for k, v in SURFACE_KILLS.items():
        monkeypatch.setenv(k, v)
    proc = start("enumerate", "10", "--db", db_url, "--workers", "2", "--json", "--quiet")
    kills = 0
    try:
        wait_for(lambda: done_count(db_url) >= 1, proc)
        while proc.poll() is None and (kills < 3 or _retries(db_url) == 0):
            try:
                proc.wait(timeout=rng.uniform(0.15, 0.6))
                break
            except subprocess.TimeoutExpired:  # still running: time for the next kill
                pass
            victims = worker_processes(proc.pid)
            if victims:
                try:
                    rng.choice(sorted(victims, key=lambda p: p.pid)).send_signal(signal.SIGKILL)
                    kills += 1
                except Exception:  # noqa: BLE001 - it was gone already
                    pass
        out, err = proc.communicate(timeout=900)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    result = json.loads(out)
    assert result["status"] == "complete" and result["total"] == 263 and kills >= 3
    assert_same_clusters(db_url, 10, reference10)
    run = _faults(db_url)
    assert run["failed"] == 0 and run["leased"] == 0 and run["retries"] > 0
    _assert_transitions_whole(db_url, 10)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [7])
def test_the_coordinator_killed_five_times_then_rerun(db_url, seed):
    """kill -9 the coordinator at five moments drawn from the seed, rerunning the same command each
    time: the last run completes with the clusters of an undisturbed one, nothing failed (a lease it
    left behind is put back without an attempt), no duplicate, every transition written once."""
    rng = random.Random(seed)
    moments = sorted(rng.sample(range(3, 50), 5))
    for moment in moments:
        proc = start("enumerate", "9", "--db", db_url, "--workers", "2", "--quiet")
        try:
            wait_for(lambda: done_count(db_url) >= moment, proc)
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=30)
        finally:
            proc.kill()
    r = cli("enumerate", "9", "--db", db_url, "--workers", "2", "--quiet", "--max-attempts", "1")
    assert r.returncode == 0, r.stderr
    assert "n = 9: 52 rigid clusters" in r.stdout and "(resumed)" in r.stdout
    assert_same_clusters(db_url, 9, list(catalogue(9).clusters))
    run = _faults(db_url)
    assert run["failed"] == 0 and run["leased"] == 0 and run["retries"] > 0
    _assert_transitions_whole(db_url, 9)
    engine = make_engine(db_url)
    with sessions(engine)() as s:
        assert s.execute(select(func.max(ExpansionRow.attempts))).scalar() == 1
        assert (
            s.execute(select(func.count()).select_from(ExpansionRow).where(ExpansionRow.status == LEASED)).scalar() == 0
        )
    engine.dispose()


def test_a_write_back_that_dies_half_way_leaves_nothing_and_is_retried(engine, monkeypatch, paper_counts):
    """The write-back of one task raises after half of its clusters are inserted (once): nothing of
    that transaction is visible, the task's expansions are retried (an attempt each: the fault is in
    the task), and the run ends with exactly the paper's clusters."""
    import packings.service.store

    real = packings.service.store.insert_or_match
    state = {"calls": 0, "raised": False}

    def dying(session, c, *a, **kw):
        state["calls"] += 1
        if not state["raised"] and state["calls"] == 6:  # within the second task's write-back, half-way
            state["raised"] = True
            raise RuntimeError("worker died mid-write (injected)")
        return real(session, c, *a, **kw)

    monkeypatch.setattr(packings.service.store, "insert_or_match", dying)
    result = _in_process_run(engine, 9, monkeypatch, lambda real_task, e, p: real_task(e, p))
    assert state["raised"] and result.status == "complete"
    assert result.by_contacts == {int(k): v for k, v in paper_counts["clusters_by_contacts"]["9"].items()}
    rows = _expansions(engine)
    retried = [e for e in rows if e.attempts == 2]
    assert retried and all(e.status == DONE for e in rows)
    with sessions(engine)() as s:
        keys = s.execute(select(ClusterRow.n, ClusterRow.certificate, ClusterRow.embedding)).all()
        every = list(queries.transitions(s))
        transitions = len(every)
        per_attempt = sum(k > 1 for k in Counter((t.source_id, t.broken, t.direction) for t in every).values())
    assert len(keys) == len(set(keys)) == 52 and per_attempt == 0 and transitions > 0


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MiB file system (tmpfs), which an n = 10 run fills mid-run: its write-ahead log grows by every
    page each write-back touches until SQLite checkpoints it (at 4 MB), and creating the schema (every
    migration in one transaction) writes about 370 KB of it first."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (needs root): {(r.stderr or r.stdout).strip()[:120]}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


@pytest.mark.slow
def test_a_full_disk_stops_the_run_in_one_line_and_it_resumes_after(small_disk, reference10):
    url = f"sqlite:///{small_disk / 'packings.db'}"
    r = cli("enumerate", "10", "--db", url, "--workers", "2", "--quiet")
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert lines[-1].startswith("packings: error: the database cannot be written (")
    assert "database or disk is full" in lines[-1] and "run the same command again" in lines[-1]
    assert all(" packings WARNING: " in line for line in lines[:-1]), lines  # only the faults logged
    done_before = done_count(url)
    assert 0 < done_before < 263
    # nothing half-written: the file is sound and nothing failed
    engine = make_engine(url)
    with engine.connect() as c:
        assert c.exec_driver_sql("PRAGMA integrity_check").scalar() == "ok"
        assert (
            c.execute(select(func.count()).select_from(ExpansionRow).where(ExpansionRow.status == FAILED)).scalar() == 0
        )
    engine.dispose()
    # space freed: the same command resumes and loses nothing
    subprocess.run(["mount", "-o", "remount,size=64m", str(small_disk)], check=True)
    r = cli("enumerate", "10", "--db", url, "--workers", "2", "--quiet")
    assert r.returncode == 0, r.stderr
    assert "n = 10: 263 rigid clusters" in r.stdout and "(resumed)" in r.stdout
    assert_same_clusters(url, 10, reference10)
    assert _faults(url)["failed"] == 0


@pytest.fixture(scope="module")
def reference8():
    return list(catalogue(8).clusters)


def test_two_runs_of_different_n_on_one_postgresql_database_at_once(pg_url, reference8):
    """Two coordinators, each with its own local cluster, on one PostgreSQL database at the same time:
    both runs complete with exactly their clusters."""
    procs = [
        start("enumerate", str(n), "--db", pg_url, "--workers", "1", "--quiet", "--dashboard-address", "127.0.0.1:0")
        for n in (8, 9)
    ]
    outs = [p.communicate(timeout=900) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err
    assert "n = 8: 13 rigid clusters" in outs[0][0] and "n = 9: 52 rigid clusters" in outs[1][0]
    assert_same_clusters(pg_url, 8, reference8)
    assert_same_clusters(pg_url, 9, list(catalogue(9).clusters))


@pytest.mark.slow
def test_four_dask_workers_and_postgresql_one_worker_killed(pg_url, reference10):
    """The many-machine setting on one machine: `dask scheduler`, four `dask worker` processes, the
    coordinator with --scheduler on PostgreSQL; one worker process is killed mid-run (its nanny starts
    another): the run completes, exact."""
    import os
    import sys

    import psutil

    dask = os.path.join(os.path.dirname(sys.executable), "dask")
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = [
        subprocess.Popen(
            [dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--dashboard-address", "127.0.0.1:0"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    ]
    try:
        wait_until_listening(port)
        procs.append(
            subprocess.Popen(
                [dask, "worker", address, "--nworkers", "4", "--nthreads", "1"],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )
        assert cli("db", "upgrade", "--db", pg_url).returncode == 0
        run = start("enumerate", "10", "--db", pg_url, "--scheduler", address, "--quiet")
        try:
            wait_for(lambda: done_count(pg_url) >= 40, run)
            nannies = psutil.Process(procs[1].pid).children()
            workers = [c for nanny in nannies for c in nanny.children()] or nannies
            assert workers, "no worker process to kill"
            sorted(workers, key=lambda p: p.pid)[0].send_signal(signal.SIGKILL)
            out, err = run.communicate(timeout=900)
        finally:
            run.kill()
        assert run.returncode == 0, err
        assert "n = 10: 263 rigid clusters" in out
        assert_same_clusters(pg_url, 10, reference10)
        status = _faults(pg_url)
        assert status["failed"] == 0 and status["leased"] == 0
    finally:
        stop(procs)


def test_a_cluster_left_without_workers_stops_the_run_resumably(engine):
    """Every worker gone for good (here: the cluster scaled to none once ten expansions are done):
    after ``workerless_timeout`` seconds without one the run stops with SchedulerError rather than
    wait for ever, its leases put back without an attempt used; a new coordinator completes it."""
    import threading

    from distributed import Client, LocalCluster

    from packings.service.coordinator import run_enumeration
    from packings.service.errors import SchedulerError

    url = engine.url.render_as_string(hide_password=False)
    with (
        LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):

        def retire():
            while done_count(url) < 10:
                time.sleep(0.05)
            cluster.scale(0)

        threading.Thread(target=retire, daemon=True).start()
        with pytest.raises(SchedulerError, match="no Dask worker for 3 s"):
            run_enumeration(engine, url, 9, Params(), client, workerless_timeout=3.0)
    rows = _expansions(engine)
    assert not any(e.status == LEASED for e in rows) and not any(e.status == FAILED for e in rows)
    assert 10 <= sum(e.status == DONE for e in rows) < 52 and max(e.attempts for e in rows) <= 1
    with (
        LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        result = run_enumeration(engine, url, 9, Params(), client, max_attempts=1)
    assert result.status == "complete" and result.total == 52 and result.resumed


def _broken_nthreads(client, monkeypatch, breaks):
    """The coordinator's own questions for the worker threads (its main thread's: the watchdog asks too)
    raise CommClosedError from the second on, as a connection that breaks as it is asked before the
    Client notices that it lost its scheduler, for the calls ``breaks`` says (call number -> bool)."""
    import threading

    from distributed.comm.core import CommClosedError

    real, calls = client.nthreads, []

    def nthreads(*args, **kwargs):
        if threading.current_thread() is threading.main_thread():
            calls.append(len(calls) + 1)
            if breaks(calls[-1]):
                raise CommClosedError("in <TCP (closed)>: ConnectionResetError: [Errno 104] Connection reset by peer")
        return real(*args, **kwargs)

    monkeypatch.setattr(client, "nthreads", nthreads)
    return calls


def test_a_connection_that_breaks_as_the_coordinator_asks_is_asked_again(engine, monkeypatch):
    """The scheduler's connection breaks twice as the coordinator asks it for the worker threads, while
    the Client still says it is running: the coordinator reaches it again and the run completes, where
    the error ended the command with a traceback."""
    from distributed import Client, LocalCluster

    import packings.service.driver
    from packings.service.coordinator import run_enumeration

    monkeypatch.setattr(packings.service.driver, "CAPACITY_SECONDS", 0.0)  # asked at every fill
    url = engine.url.render_as_string(hide_password=False)
    with (
        LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        calls = _broken_nthreads(client, monkeypatch, lambda k: k in (2, 3))
        result = run_enumeration(engine, url, 9, Params(), client, max_attempts=1)
    assert result.status == "complete" and result.total == 52 and result.errors == []
    assert len(calls) > 3
    assert all(e.status == DONE and e.attempts == 1 for e in _expansions(engine))


def test_a_connection_that_stays_broken_stops_the_run_resumably(engine, monkeypatch):
    """The connection breaks at every question from the second on, longer than the Client's window to
    reach its scheduler again: the run stops with SchedulerError, its leases put back without an attempt
    used, and a new coordinator completes it."""
    from distributed import Client, LocalCluster

    import packings.service.driver
    from packings.service.coordinator import run_enumeration
    from packings.service.errors import SchedulerError

    monkeypatch.setattr(packings.service.driver, "CAPACITY_SECONDS", 0.0)
    monkeypatch.setattr(packings.service.driver, "RECONNECT_MARGIN", 1.0)
    url = engine.url.render_as_string(hide_password=False)
    with (
        LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        client._timeout = 1.0
        _broken_nthreads(client, monkeypatch, lambda k: k >= 2)
        with pytest.raises(SchedulerError, match="could not reach it again"):
            run_enumeration(engine, url, 9, Params(), client)
    rows = _expansions(engine)
    assert not any(e.status == LEASED for e in rows) and max(e.attempts for e in rows) <= 1
    with (
        LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        result = run_enumeration(engine, url, 9, Params(), client, max_attempts=1)
    assert result.status == "complete" and result.total == 52 and result.resumed


def test_a_local_worker_its_nanny_could_not_restart_is_replaced(monkeypatch):
    """A worker process killed while its nanny could not start it again (here: the nanny's start made
    to fail) leaves a slot without a worker for good; revive_workers gives it a new nanny and worker."""
    import os

    import packings.service.dask_cluster as dc

    monkeypatch.setattr(dc, "REVIVE_SECONDS", 1.0)
    with dc.dask_client(None, 2, quiet=True) as d:
        client = d.client
        client.wait_for_workers(2, timeout=120)
        name, nanny = sorted(d.cluster.workers.items())[0]

        async def cannot_start():
            raise RuntimeError("injected: the new worker process died as it started")

        nanny.instantiate = cannot_start
        os.kill(nanny.process.pid, signal.SIGKILL)
        wait_for(lambda: len(client.nthreads()) == 1, timeout=60, interval=0.2, what="the slot is empty")
        replaced = wait_for(d.revive_workers, timeout=60, interval=0.3, what="revive_workers replaces one")
        assert replaced == 1 and d.cluster.workers.get(name) is not nanny  # the nanny that gave up is gone
        client.wait_for_workers(2, timeout=120)
        # Dask's SpecCluster records a new nanny once its start has returned, which can be after its worker
        # has joined the scheduler: wait for the record too
        wait_for(lambda: len(d.cluster.workers) == 2, timeout=60, interval=0.2, what="the new nanny is recorded")
        assert len(client.nthreads()) == 2 and all(n is not nanny for n in d.cluster.workers.values())


def test_fresh_workers_replaces_the_local_worker_processes():
    """dask_client.fresh_workers: the local cluster's worker processes are new ones, set up with the
    plugins as the first were, and take tasks; an existing cluster's workers are left alone."""
    import os

    import packings.service.dask_cluster as dc

    with dc.dask_client(None, 2, quiet=True) as d:
        client = d.client
        client.wait_for_workers(2, timeout=120)
        before = set(client.run(os.getpid).values())
        assert d.fresh_workers()
        client.wait_for_workers(2, timeout=120)
        after = set(client.run(os.getpid).values())
        assert len(after) == 2 and not before & after
        plugins = client.run(lambda dask_worker: sorted(dask_worker.plugins))
        assert all("packings-local-worker" in names for names in plugins.values())
        assert client.submit(sum, [1, 2]).result() == 3
    assert dc.dask_client("tcp://127.0.0.1:1", None, True).fresh_workers() is False


class _DaskCluster:
    """`dask scheduler` and `dask worker` processes on one port, started again as an operator's
    supervisor would (a Dask worker ends when it loses its scheduler).  With ``page``, the database
    whose runs the scheduler's packings page shows (``--preload packings.service.dashboard``), served
    on :attr:`dashboard_port`."""

    def __init__(self, workers: int = 2, page: str | None = None):
        import os
        import sys

        self.dask = os.path.join(os.path.dirname(sys.executable), "dask")
        self.port, self.workers, self.page = free_port(), workers, page
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.dashboard_port = free_port() if page else 0
        self.scheduler = self.worker = None

    def start(self) -> None:
        import os

        self.scheduler = subprocess.Popen(
            [
                self.dask,
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--dashboard-address",
                f"127.0.0.1:{self.dashboard_port}",
                *(["--preload", "packings.service.dashboard"] if self.page else []),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env={**os.environ, "PACKINGS_DB": self.page} if self.page else None,
        )
        wait_until_listening(self.port)
        self.worker = subprocess.Popen(
            [self.dask, "worker", self.address, "--nworkers", str(self.workers), "--nthreads", "1"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )

    def kill_worker(self) -> str:
        """kill -9 one worker process (its nanny starts another, at a new address); its address."""
        import os

        from distributed import Client

        with Client(self.address, timeout="30s") as client:
            client.wait_for_workers(self.workers, timeout=60)
            address, pid = sorted(client.run(os.getpid).items())[0]
        os.kill(pid, signal.SIGKILL)
        return address

    def kill_scheduler(self) -> None:
        self.scheduler.send_signal(signal.SIGKILL)
        self.scheduler.wait(timeout=30)
        try:  # its workers end on their own once they lose it
            self.worker.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.worker.kill()

    def stop(self) -> None:
        stop([p for p in (self.scheduler, self.worker) if p is not None])


def _scheduler_lost_mid_run(cluster: _DaskCluster, url: str, back_after: float | None) -> tuple[int, str, str]:
    """`packings enumerate 10 --scheduler` on ``cluster``, whose scheduler is killed once 40 expansions
    are done and started again ``back_after`` seconds later (None: never); the run's exit status and
    output."""
    cluster.start()
    assert cli("db", "upgrade", "--db", url).returncode == 0
    run = start("enumerate", "10", "--db", url, "--scheduler", cluster.address, "--quiet")
    try:
        wait_for(lambda: done_count(url) >= 40, run)
        cluster.kill_scheduler()
        if back_after is not None:
            time.sleep(back_after)
            cluster.start()
        out, err = run.communicate(timeout=900)
    finally:
        run.kill()
    return run.returncode, out, err


@pytest.mark.slow
def test_a_worker_lost_under_an_external_scheduler_is_logged_counted_and_shown(pg_url, reference10):
    """kill -9 of one `dask worker` process during `enumerate --scheduler` on PostgreSQL: Dask runs its
    tasks again on the other worker by itself (no KilledWorker reaches the coordinator), and yet the
    loss is logged in one line without -v, counted in the retries that `packings status` shows, and on
    the scheduler's packings page, whose workers table no longer lists the dead worker; the run
    completes, exact."""
    from packings.service.dashboard import _html
    from tests.helpers import fetch

    cluster = _DaskCluster(workers=2, page=pg_url)
    try:
        cluster.start()
        assert cli("db", "upgrade", "--db", pg_url).returncode == 0
        run = start("enumerate", "10", "--db", pg_url, "--scheduler", cluster.address, "--no-glued")
        try:
            wait_for(lambda: done_count(pg_url) >= 40, run)
            victim = cluster.kill_worker()
            out, err = run.communicate(timeout=900)
        finally:
            run.kill()
        assert run.returncode == 0, err
        assert "n = 10: 263 rigid clusters" in out
        lost = [line for line in err.splitlines() if "was lost" in line]
        assert len(lost) == 1 and f"Dask worker {victim} was lost with " in lost[0], err
        assert " packings WARNING: " in lost[0] and "counted in retries" in lost[0]
        # the scheduler serves the packings page (its preload): the link printed is the page's
        assert f"; dashboard http://127.0.0.1:{cluster.dashboard_port}/packings\n" in err, err
        assert_same_clusters(pg_url, 10, reference10)
        status = _faults(pg_url)
        assert status["retries"] > 0 and status["failed"] == 0 and status["leased"] == 0
        table = cli("status", "--db", pg_url).stdout
        assert "retries" in table.splitlines()[0] and str(status["retries"]) in table.splitlines()[1].split()
        url = f"http://127.0.0.1:{cluster.dashboard_port}/packings.json"
        deadline = time.monotonic() + 60
        while True:  # the page reads the database every second or so
            snap = json.loads(fetch(url)[1])
            if snap.get("retries") == status["retries"] and snap.get("frontier", {}).get("done") == 263:
                break
            assert time.monotonic() < deadline, snap
            time.sleep(0.5)
        assert victim in snap["workers_gone"] and victim not in {w["worker"] for w in snap["workers"]}
        assert snap["workers_live"] == 2  # the nanny's new worker
        page = _html(snap)
        assert f"{status['retries']} retries" in page and victim in page
    finally:
        cluster.stop()


@pytest.mark.slow
def test_the_scheduler_restarted_mid_run_the_coordinator_reconnects_and_completes(pg_url, reference10):
    """With --scheduler, the scheduler is killed mid-run and started again on its port 3 s later (with
    new workers, as a supervisor restarts them): the coordinator reaches it again, puts the lost tasks'
    expansions back without using up attempts, registers the database plugin with the new scheduler,
    and the run completes, exact."""
    cluster = _DaskCluster()
    try:
        code, out, err = _scheduler_lost_mid_run(cluster, pg_url, back_after=3.0)
        assert code == 0, err
        assert "lost the Dask scheduler; trying to reach it again" in err
        assert "reached the Dask scheduler again" in err and "Traceback" not in err
        assert "n = 10: 263 rigid clusters" in out
        assert_same_clusters(pg_url, 10, reference10)
        status = _faults(pg_url)
        assert status["failed"] == 0 and status["leased"] == 0 and status["retries"] > 0
        _assert_transitions_whole(pg_url, 10)
    finally:
        cluster.stop()


@pytest.mark.slow
def test_a_scheduler_that_does_not_come_back_ends_the_run_in_one_line_resumably(pg_url, reference10, monkeypatch):
    """The scheduler is killed for good: after the reconnection window (PACKINGS_RECONNECT_SECONDS) the
    coordinator stops with one line and exit 1, its leases put back; the same run then completes on a
    new scheduler."""
    monkeypatch.setenv("PACKINGS_RECONNECT_SECONDS", "3")
    cluster = _DaskCluster()
    try:
        code, out, err = _scheduler_lost_mid_run(cluster, pg_url, back_after=None)
        assert code == 1 and "Traceback" not in err, err
        # nothing but the faults logged and the one line (no Dask "distributed.client - ERROR" before it)
        errors = [line for line in err.splitlines() if line.strip() and " packings WARNING: " not in line]
        assert len(errors) == 1 and errors[0].startswith(
            "packings: error: lost the Dask scheduler and could not reach it again in"
        ), err
        assert errors[0].endswith("run the same command to resume")
        status = _faults(pg_url)
        assert status["leased"] == 0 and status["status"] != "complete" and status["done"] >= 40
        cluster.start()
        r = cli("enumerate", "10", "--db", pg_url, "--scheduler", cluster.address, "--quiet")
        assert r.returncode == 0 and "n = 10: 263 rigid clusters" in r.stdout, r.stderr
        assert_same_clusters(pg_url, 10, reference10)
    finally:
        cluster.stop()
    monkeypatch.setenv("PACKINGS_RECONNECT_SECONDS", "soon")
    r = cli("enumerate", "10", "--db", pg_url, "--scheduler", cluster.address)
    assert r.returncode != 0 and r.stderr.strip().splitlines() == [
        "packings: error: PACKINGS_RECONNECT_SECONDS must be a positive number of seconds (got 'soon')"
    ], r.stderr
