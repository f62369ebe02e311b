"""``packings enumerate`` end to end: the real CLI, a real Dask LocalCluster, each backend.

Also the fault-tolerance promises: a worker process killed mid-run, and the
coordinator killed mid-run and the same command run again, end with exactly
the clusters of an uninterrupted run, no duplicates and nothing left leased.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import pytest
from sqlalchemy import func, select

from benchmarks.soak import worker_processes
from packings.service.db import make_engine, sessions
from packings.service.models import LEASED, ClusterRow, ExpansionRow
from packings.workers.params import Params
from tests.helpers import (
    assert_same_clusters,
    catalogue,
    done_count,
    free_port,
    packings,
    start,
    stop,
    wait_for,
    wait_until_listening,
)


@pytest.fixture(scope="module")
def reference9():
    """The uninterrupted in-memory enumeration of n = 9 (packings.workers.explore)."""
    return list(catalogue(9).clusters)


def test_enumerate_9_with_a_local_cluster(db_url, reference9, paper_counts):
    r = packings("enumerate", "9", "--db", db_url, "--workers", "2", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["total"] == paper_counts["totals"]["9"] == 52
    assert out["by_contacts"] == paper_counts["clusters_by_contacts"]["9"]
    assert out["status"] == "complete" and out["diagnostics"]["failed_tasks"] == 0
    assert_same_clusters(db_url, 9, reference9)
    # the same command again resumes the complete run: nothing new, same table
    r2 = packings("enumerate", "9", "--db", db_url, "--json", "--quiet")
    assert r2.returncode == 0, r2.stderr
    again = json.loads(r2.stdout)
    assert again["run"] == out["run"] and again["by_contacts"] == out["by_contacts"]
    # its time: the first run's, and a moment now
    assert again["total_seconds"] >= out["seconds"] > again["seconds"]
    assert_same_clusters(db_url, 9, reference9)
    # and stats reads the same counts
    r3 = packings("stats", "--json", "--db", db_url)
    (stats,) = json.loads(r3.stdout)
    assert (stats["n"], stats["total"], stats["by_contacts"], stats["unclassified"]) == (9, 52, {"21": 52}, 0)


def test_enumerate_prints_the_table_the_dashboard_and_progress(sqlite_url):
    r = packings("enumerate", "7", "--db", sqlite_url, "--workers", "1")
    assert r.returncode == 0, r.stderr
    assert "n = 7: 5 rigid clusters" in r.stdout and "diagnostics:" in r.stdout
    assert "dashboard http://127.0.0.1:" in r.stderr
    assert "expansions" in r.stderr and "clusters 5" in r.stderr
    assert " packings " not in r.stderr  # nothing logged: no fault to report
    # -v logs what the run does
    r = packings("-v", "enumerate", "7", "--db", sqlite_url, "--workers", "1", "--quiet")
    assert r.returncode == 0, r.stderr
    assert "packings INFO: run 1 (n = 7): resumed" in r.stderr and "packings INFO: run 1 (n = 7): complete" in r.stderr


def test_lines_written_during_a_run_are_not_written_over_the_bar(sqlite_url):
    """The bar is drawn from the run's first progress on (not while the cluster starts, whose line came
    after it on the same line), and what is logged while it is drawn ("complete after", with -v, before
    the bar closes) is on a line of its own: each line of standard error, after its last carriage
    return, is the bar or one message, never the bar followed by a message."""
    import re

    r = packings("-v", "enumerate", "8", "--db", sqlite_url, "--workers", "1", "--no-glued")
    assert r.returncode == 0, r.stderr
    shown = [line.rsplit("\r", 1)[-1] for line in r.stderr.split("\n")]
    assert any(line.startswith("dask: local cluster") for line in shown), r.stderr
    complete = [line for line in shown if "): complete after" in line]
    assert len(complete) == 1 and re.match(r"\d\d:\d\d:\d\d packings INFO: run 1", complete[0]), r.stderr
    assert "dask: local cluster" not in r.stderr.split("expansions:", 1)[1], r.stderr  # the bar starts after it
    assert not re.search(r"exp/s[^\r\n]*\]\S", r.stderr), r.stderr  # nothing written right after a bar


@pytest.mark.slow
def test_enumerate_10(db_url, paper_counts, reference10):
    r = packings("enumerate", "10", "--db", db_url, "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["total"] == 263
    assert out["by_contacts"] == paper_counts["clusters_by_contacts"]["10"] == {"23": 1, "24": 259, "25": 3}
    # two workers finishing in their own order store the same clusters as the serial enumeration
    assert_same_clusters(db_url, 10, reference10)


def test_killing_a_worker_mid_run(db_url, reference9):
    proc = start("enumerate", "9", "--db", db_url, "--workers", "2", "--quiet")
    try:
        wait_for(lambda: done_count(db_url) >= 8, proc)
        victims = worker_processes(proc.pid)
        assert len(victims) == 2, [p.cmdline() for p in victims]
        victims[0].send_signal(signal.SIGKILL)
        out, err = proc.communicate(timeout=600)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "n = 9: 52 rigid clusters" in out
    assert not victims[0].is_running()
    assert_same_clusters(db_url, 9, reference9)


def test_killing_the_coordinator_mid_run_then_resuming(db_url, reference9):
    proc = start("enumerate", "9", "--db", db_url, "--workers", "2", "--quiet")
    try:
        wait_for(lambda: done_count(db_url) >= 10, proc)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        proc.kill()
    assert 10 <= done_count(db_url) < 52
    engine = make_engine(db_url)
    with sessions(engine)() as s:
        leased = s.execute(select(func.count()).select_from(ExpansionRow).where(ExpansionRow.status == LEASED)).scalar()
    engine.dispose()
    assert leased > 0  # the dead coordinator left leases behind
    r = packings("enumerate", "9", "--db", db_url, "--workers", "2", "--quiet")
    assert r.returncode == 0, r.stderr
    assert "n = 9: 52 rigid clusters" in r.stdout and "(resumed)" in r.stdout
    assert f"{leased} expansion(s) leased by a coordinator that is gone put back to pending" in r.stderr
    assert_same_clusters(db_url, 9, reference9)


def test_an_unreachable_scheduler_is_one_line(sqlite_url, tmp_path):
    r = packings("enumerate", "7", "--db", sqlite_url, "--scheduler", "tcp://127.0.0.1:1", "--quiet")
    assert r.returncode != 0 and "Traceback" not in r.stderr
    lines = [l for l in r.stderr.strip().splitlines() if l.strip()]
    assert len(lines) == 1 and "cannot reach the Dask scheduler" in lines[0], r.stderr
    assert list(tmp_path.iterdir()) == []  # no database file was created


def test_workers_and_scheduler_are_exclusive(tmp_path):
    r = packings("enumerate", "7", "--workers", "2", "--scheduler", "tcp://127.0.0.1:8786", cwd=tmp_path)
    assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_joining_an_existing_dask_cluster(db_url, paper_counts):
    """The README's many-machine recipe on one machine: `dask scheduler`, `dask worker`, `--scheduler`."""
    import os

    dask = os.path.join(os.path.dirname(sys.executable), "dask")
    port, dash = free_port(), free_port()
    address = f"tcp://127.0.0.1:{port}"
    # the scheduler serves the packings page of the database it is told (README: many machines)
    procs = [
        subprocess.Popen(
            [
                dask,
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--dashboard-address",
                f"127.0.0.1:{dash}",
                "--preload",
                "packings.service.dashboard",
            ],
            stderr=subprocess.DEVNULL,
            env={**os.environ, "PACKINGS_DB": db_url},
        )
    ]
    try:
        wait_until_listening(port)  # as an operator starts the scheduler before pointing anything at it
        procs.append(
            subprocess.Popen([dask, "worker", address, "--nworkers", "2", "--nthreads", "1"], stderr=subprocess.DEVNULL)
        )
        r = packings("db", "upgrade", "--db", db_url)
        assert r.returncode == 0, r.stderr
        r = packings("enumerate", "8", "--db", db_url, "--scheduler", address, "--json")
        assert r.returncode == 0, r.stderr
        out = json.loads(r.stdout)
        assert out["by_contacts"] == paper_counts["clusters_by_contacts"]["8"]
        assert f"dashboard http://127.0.0.1:{dash}/packings" in r.stderr  # the scheduler serves the page
        # the workers wrote the results themselves: every expansion names a worker of that cluster
        engine = make_engine(db_url)
        with sessions(engine)() as s:
            workers = {w for (w,) in s.execute(select(ExpansionRow.worker))}
        engine.dispose()
        assert workers and all(w.startswith("tcp://127.0.0.1:") for w in workers)
        # the page's data: the run as the database has it (read every second)
        import urllib.request

        def page() -> dict | None:
            with urllib.request.urlopen(f"http://127.0.0.1:{dash}/packings.json", timeout=10) as r:
                snap = json.loads(r.read())
            return snap if snap.get("status") == "complete" else None

        snap = wait_for(page, timeout=60, interval=0.5, what="the page shows the run complete")
        assert (snap["run"], snap["n"], snap["status"], snap["clusters"]) == (out["run"], 8, "complete", 13)
        assert snap["frontier"] == {"pending": 0, "leased": 0, "done": 13, "failed": 0}
        # Dask's own panels name the tasks by run: their keys carry n
        from distributed import Client

        with Client(address, timeout="30s") as client:
            prefixes = client.run_on_scheduler(lambda dask_scheduler: sorted(dask_scheduler.task_prefixes))
        assert "expand_n8" in prefixes, prefixes
    finally:
        stop(procs)


def test_failing_tasks_are_retried_through_dask_then_reported(engine, monkeypatch):
    """A task that always fails is tried max_attempts times, then the run ends incomplete with its error."""
    from distributed import Client, LocalCluster

    import packings.service.tasks
    from packings.service.coordinator import run_enumeration

    def broken(cluster, params, arrivals=()):
        raise FloatingPointError("injected failure")

    monkeypatch.setattr(
        packings.service.tasks, "expand", broken
    )  # threads of this process: the patch reaches the tasks
    url = engine.url.render_as_string(hide_password=False)
    with (
        LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        result = run_enumeration(engine, url, 6, Params(), client, max_attempts=2)
    assert result.status == "incomplete"
    assert result.errors == ["expansion 1: FloatingPointError: injected failure"]
    assert result.diagnostics["failed_tasks"] == 1
    with sessions(engine)() as s:
        e = s.get(ExpansionRow, 1)
        assert e.status == "failed" and e.attempts == 2 and e.lease_token is None
        # the database keeps the whole traceback, down to the function that raised
        assert e.error.startswith("Traceback (most recent call last)") and "in broken" in e.error
        assert e.error.splitlines()[-1] == "FloatingPointError: injected failure"


def test_a_failing_expansion_does_not_fail_the_others_of_its_task(engine, monkeypatch):
    """A task expands several clusters.  One whose expansion fails is retried on its own and then
    marked failed; the others of its task are written back, and the run reaches everything else."""
    from distributed import Client, LocalCluster

    import packings.service.coordinator
    import packings.service.tasks
    from packings.service.coordinator import run_enumeration
    from packings.workers.identity import same_geometry

    params = Params()
    victim = catalogue(8).clusters[3]
    real_expand, real_task = packings.service.tasks.expand, packings.service.coordinator.expand_task
    batches: list[list[int]] = []
    monkeypatch.setattr(
        packings.service.tasks, "seen_batches", batches, raising=False
    )  # tasks are pickled: reach it by module

    def failing(cluster, p, arrivals=()):
        if same_geometry(cluster, victim, p.tol_d):
            raise FloatingPointError("injected failure")
        return real_expand(cluster, p, arrivals)

    def recording(expansions, plugin):
        packings.service.tasks.seen_batches.append([eid for eid, _ in expansions])
        return real_task(expansions, plugin)

    monkeypatch.setattr(packings.service.tasks, "expand", failing)
    monkeypatch.setattr(packings.service.coordinator, "expand_task", recording)
    url = engine.url.render_as_string(hide_password=False)
    with (
        LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        result = run_enumeration(engine, url, 8, params, client, max_attempts=2, per_worker=1, batch=4)
    assert result.status == "incomplete"
    with sessions(engine)() as s:
        rows = s.execute(
            select(ExpansionRow, ClusterRow).join(ClusterRow, ClusterRow.id == ExpansionRow.cluster_id)
        ).all()
    failed = [(e, c) for e, c in rows if e.status == "failed"]
    assert len(failed) == 1 and same_geometry(failed[0][1].to_core(), victim, params.tol_d)
    e = failed[0][0]
    assert any(len(b) > 1 and e.id in b for b in batches), batches  # it shared a task with others
    assert e.attempts == 2 and e.lease_token is None
    assert result.errors == [f"expansion {e.id}: FloatingPointError: injected failure"]
    assert all(e.status == "done" for e, _ in rows if e is not failed[0][0])
    assert len(rows) >= 2 and result.diagnostics["failed_tasks"] == 1


def test_claimed_expansions_are_shared_out_evenly():
    from packings.service.coordinator import _shares

    claimed = [(i, f"t{i}") for i in range(11)]
    parts = _shares(claimed, 4)
    assert [len(p) for p in parts] == [3, 3, 3, 2]
    assert [x for p in parts for x in p] == claimed
    assert [len(p) for p in _shares(claimed[:3], 8)] == [1, 1, 1]  # a small frontier: one each, no empty task
    assert _shares([], 4) == [] and _shares(claimed, 0) == []


def test_the_last_expansions_of_a_run_go_out_in_small_tasks():
    """While the frontier is large a task takes ``batch`` expansions; once a claim takes all that is
    pending, what it took is spread over as many tasks as the workers hold, so that one worker does not
    hold them all in one task while another has none."""
    from packings.service.coordinator import _task_count

    assert _task_count(32, 4, 8, 8) == 4  # a full claim: the tasks wanted, eight each
    assert _task_count(20, 4, 8, 8) == 8  # the frontier ran out: spread over the capacity
    assert _task_count(3, 4, 8, 8) == 4  # fewer than the tasks wanted: one each (_shares leaves none empty)
    assert _task_count(6, 2, 8, 8) == 6


def test_the_max_attempts_option_reaches_the_coordinator(sqlite_url, monkeypatch):
    from contextlib import nullcontext
    from types import SimpleNamespace

    from click.testing import CliRunner

    import packings.service.cli
    import packings.service.coordinator
    import packings.service.run
    from packings.service.coordinator import RunResult

    seen = {}

    def fake_run(engine, url, n, params, client, on_progress=None, max_attempts=3, **kw):
        seen["max_attempts"] = max_attempts
        return RunResult(1, n, "complete", {}, {}, 0.0, False)

    monkeypatch.setattr(packings.service.coordinator, "run_enumeration", fake_run)
    monkeypatch.setattr(
        packings.service.run,
        "dask_client",
        lambda *a, **kw: nullcontext(SimpleNamespace(client=None, revive_workers=lambda: 0)),
    )
    r = CliRunner().invoke(
        packings.service.cli.cli,
        ["enumerate", "6", "--db", sqlite_url, "--max-attempts", "7", "--quiet", "--no-glued"],
    )
    assert r.exit_code == 0, r.output
    assert seen == {"max_attempts": 7}


def test_each_worker_compiles_the_kernels_when_it_joins(engine):
    """The plugin warms the compiled kernels up in every worker process when it is registered,
    before any task runs, so no task pays for compilation."""
    from distributed import Client, LocalCluster

    from packings.service.plugin import DatabasePlugin

    url = engine.url.render_as_string(hide_password=False)
    plugin = DatabasePlugin(url)

    def compiled(dask_worker):
        import packings.workers._compiled as c

        return dask_worker.plugins[plugin.name].warm_up_seconds, len(c.newton.signatures), len(c.residual.signatures)

    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        client.register_plugin(plugin)
        seen = client.run(compiled)
    assert len(seen) == 2
    for seconds, newton, residual in seen.values():
        assert seconds > 0.0 and newton >= 1 and residual >= 1


def test_a_local_cluster_sets_its_workers_up_as_they_start(engine):
    """``packings enumerate`` gives its local cluster the plugin when it starts it (in the background,
    while the database is opened): each worker has its engine, has warmed the kernels up and has
    frozen what it loaded out of the garbage collector's way before it joins and any task runs."""
    import gc

    import packings.service.dask_cluster
    from packings.service.plugin import DatabasePlugin

    plugin = DatabasePlugin(engine.url.render_as_string(hide_password=False))

    def state(dask_worker):
        p = dask_worker.plugins.get(plugin.name)
        return p is not None and p.engine is not None, getattr(p, "warm_up_seconds", 0.0), gc.get_freeze_count()

    with packings.service.dask_cluster.dask_client(None, 2, True, plugins=(plugin,)) as local:
        seen = local.client.run(state)
    assert len(seen) == 2
    for has_engine, warm_up_seconds, frozen in seen.values():
        assert has_engine and warm_up_seconds > 0.0 and frozen > 10_000


def _worker_origin():
    """What a worker process tells of how it started (run in it)."""
    import os

    preload = sys.modules.get("packings.service.preload")
    return (
        os.getppid(),
        preload is not None,
        getattr(preload, "warm_up_seconds", 0.0),
        os.environ.get("OMP_NUM_THREADS"),
        os.environ.get("MALLOC_TRIM_THRESHOLD_"),
    )


@pytest.fixture
def fresh_dask_config(monkeypatch):
    """Dask's configuration read again from the environment (as a new process would), and again after."""
    import dask

    dask.config.refresh()
    yield monkeypatch
    monkeypatch.undo()
    dask.config.refresh()


@pytest.mark.skipif(
    "forkserver" not in __import__("multiprocessing").get_all_start_methods(),
    reason="this platform has no fork server: local workers are spawned",
)
def test_a_local_clusters_workers_are_forked_warm_from_one_fork_server(engine, fresh_dask_config):
    """The local cluster's workers are forked from one fork server that imported the tasks' modules and
    warmed the kernels up before (packings.service.preload), not spawned by this process to import it all each
    again; they have the environment Dask gives new worker processes (one BLAS thread, malloc trim)."""
    import os

    import packings.service.dask_cluster
    from packings.service.plugin import DatabasePlugin

    fresh_dask_config.delenv(packings.service.dask_cluster.METHOD_ENV, raising=False)
    plugin = DatabasePlugin(engine.url.render_as_string(hide_password=False))
    with packings.service.dask_cluster.dask_client(None, 2, True, plugins=(plugin,)) as local:
        seen = local.client.run(_worker_origin)
    assert len(seen) == 2
    parents = {parent for parent, *_ in seen.values()}
    assert len(parents) == 1 and os.getpid() not in parents, "one parent, the fork server, for both"
    for _, preloaded, preload_warm_up, omp, trim in seen.values():
        assert preloaded and preload_warm_up > 0.0, "the fork server had loaded and warmed up the kernels"
        assert (omp, trim) == ("1", "65536")


def test_a_chosen_start_method_is_kept(engine, fresh_dask_config):
    """A user who chose how Dask starts its workers (the environment variable) gets that: here spawned
    by this process, and no fork server is started for them."""
    import os

    import dask

    import packings.service.dask_cluster

    fresh_dask_config.setenv(packings.service.dask_cluster.METHOD_ENV, "spawn")
    dask.config.refresh()
    assert packings.service.dask_cluster.start_fork_server() is False
    with packings.service.dask_cluster.dask_client(None, 1, True) as local:
        seen = local.client.run(_worker_origin)
    ((parent, preloaded, *_),) = seen.values()
    assert parent == os.getpid() and not preloaded


def test_the_command_line_starts_the_workers_before_loading_the_kernels():
    """What ``packings enumerate`` imports before it starts its local cluster (the command line and the
    worker plugin) leaves out the numerical code: the workers start while it is loaded."""
    code = (
        "import sys, packings.service.cli, packings.service.plugin; "
        "print(sorted(m for m in ('numba', 'packings.workers.expand', 'packings.workers.kernels', 'packings.service.store') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_command_line_loads_light_so_that_the_fork_server_starts_first():
    """Importing the command line loads none of SQLAlchemy, numpy, Dask (0.3 s in all): `packings
    enumerate` starts its workers' fork server before it loads them, and the commands load what they use."""
    code = (
        "import sys, packings.service.cli; "
        "print(sorted(m for m in ('sqlalchemy', 'numpy', 'dask', 'distributed') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_coordinator_never_loads_the_path_following_code(tmp_path):
    """The coordinator (and every command that only reads or writes the database) creates a run, seeds
    it, claims, submits and counts without importing the path-following code and numba (a quarter of a
    second of a run's start-up, on the cores the workers need)."""
    code = (
        "import sys\n"
        "from packings.service import coordinator, queries, store\n"
        "from packings.service.db import open_database, sessions\n"
        "from packings.workers.params import Params\n"
        f"S = sessions(open_database('sqlite:///{tmp_path / 'c.db'}', create=True))\n"
        "info = store.start_run(S, 8, Params(), 'here:1')\n"
        "assert store.claim(S, info.id, 'here:1', 8)\n"
        "with S() as s:\n"
        "    queries.run_counts(s, info.id), queries.run_diagnostics(s, info.id)\n"
        "print(sorted(m for m in ('numba', 'packings.workers._compiled', 'packings.workers.paths', 'packings.workers.expand') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("env, expected", [(None, False), ("True", True)])
def test_local_workers_do_not_profile_unless_asked(fresh_dask_config, env, expected):
    """Dask's statistical profiler (a stack sample every 10 ms) costs a run about 8 %: the local
    cluster of ``packings enumerate`` starts its workers without it, unless the variable asks."""
    import dask

    import packings.service.dask_cluster

    fresh_dask_config.delenv(packings.service.dask_cluster.PROFILE_ENV, raising=False)
    if env is not None:
        fresh_dask_config.setenv(packings.service.dask_cluster.PROFILE_ENV, env)
    dask.config.refresh()  # read the environment as a new process would
    with packings.service.dask_cluster.dask_client(None, 1, True) as local:
        seen = local.client.run(lambda: dask.config.get("distributed.worker.profile.enabled"))
    assert list(seen.values()) == [expected]


def _one(i: int) -> int:
    return i


@pytest.mark.parametrize("env", [None, "1000"])
def test_the_coordinator_keeps_few_of_the_messages_it_sent(fresh_dask_config, env):
    """Dask keeps, for each stream of messages (client to scheduler, scheduler to each worker and to the
    client), the last ``distributed.admin.low-level-log-length`` messages it sent, each task's spec
    among them: with Dask's 1,000 the coordinator's process grew with every task it submitted.  The
    local cluster of ``packings enumerate`` and its Client keep :data:`LOG_LENGTH` of them, unless the
    variable asks for another number."""
    import dask

    import packings.service.dask_cluster as dc

    fresh_dask_config.delenv(dc.LOG_LENGTH_ENV, raising=False)
    if env is not None:
        fresh_dask_config.setenv(dc.LOG_LENGTH_ENV, env)
    dask.config.refresh()  # read the environment as a new process would
    with dc.dask_client(None, 1, True) as local:
        client = local.client
        for i in range(dc.LOG_LENGTH + 60):  # one at a time: a message (a batch) each way per task
            assert client.submit(_one, i, key=f"one-{i}").result() == i
        scheduler = local.cluster.scheduler
        held = [
            len(client.scheduler_comm.recent_message_log),
            *(len(b.recent_message_log) for b in scheduler.stream_comms.values()),
            *(len(b.recent_message_log) for b in scheduler.client_comms.values()),
        ]
    if env is None:
        assert max(held) <= dc.LOG_LENGTH
    else:
        assert max(held) > dc.LOG_LENGTH + 50


def _kinds(scheduler) -> list[int]:
    """How many collections Dask's scheduler recorded in the metadata of each of its spans (one each
    submission of tasks that joined it)."""
    return [len((span.metadata or {}).get("collections", ())) for span in scheduler.extensions["spans"].spans.values()]


def test_the_scheduler_forgets_what_each_task_left_once_it_is_gone(fresh_dask_config, monkeypatch):
    """Dask's scheduler adds the kind of collection of every submission (``{"type": "Future"}``) to the
    metadata of the span its tasks join and never shortens that list, and splits each task's key through a
    cache of up to 100,000 keys: both grew by a few hundred bytes with every task ``packings enumerate``
    submitted.  The scheduler of ``dask_client`` has :class:`packings.service.plugin.TaskLeftovers`, which keeps one
    entry of each kind and empties the cache past :data:`packings.service.plugin.KEY_CACHE_LIMIT`; without it both
    grow.  Tasks are kept in flight, as the coordinator keeps them: they all join one span."""
    from dask.utils import key_split

    import packings.service.dask_cluster as dc
    import packings.service.plugin

    monkeypatch.setattr(packings.service.plugin, "KEY_CACHE_LIMIT", 20)  # the scheduler runs in this process
    with dc.dask_client(None, 1, True) as local:
        client, scheduler = local.client, local.cluster.scheduler
        assert packings.service.plugin.TaskLeftovers.name in scheduler.plugins
        key_split.cache_clear()
        assert client.gather([client.submit(_one, i, key=f"left-{i}") for i in range(60)]) == list(range(60))
        kinds, keys = _kinds(scheduler), key_split.cache_info().currsize
        client.unregister_scheduler_plugin(packings.service.plugin.TaskLeftovers.name)
        assert client.gather([client.submit(_one, i, key=f"right-{i}") for i in range(60)]) == list(range(60))
        grown, grown_keys = _kinds(scheduler), key_split.cache_info().currsize
    assert max(kinds) == 1 and keys < 30  # the limit, and the few keys split since the last submission
    assert max(grown) >= 60 and grown_keys >= 60  # Dask's own behaviour, which the plugin bounds


def test_a_worker_empties_its_cache_of_task_keys_as_tasks_are_forgotten(monkeypatch, tmp_path):
    """A worker splits each task's key through the same cache as the scheduler: its database plugin empties
    it, once past the limit, as the worker forgets a task."""
    from dask.utils import key_split

    import packings.service.plugin

    monkeypatch.setattr(packings.service.plugin, "KEY_CACHE_LIMIT", 5)
    plugin = packings.service.plugin.DatabasePlugin(f"sqlite:///{tmp_path / 'db.sqlite'}")
    key_split.cache_clear()
    for i in range(5):
        key_split(f"kept-{i}")
    plugin.transition("kept-0", "released", "forgotten")
    assert key_split.cache_info().currsize == 5  # not past the limit: kept
    key_split("kept-5")
    plugin.transition("kept-5", "memory", "released")
    assert key_split.cache_info().currsize == 6  # not forgotten yet
    plugin.transition("kept-5", "released", "forgotten")
    assert key_split.cache_info().currsize == 0


def test_a_scheduler_started_with_the_preload_has_the_plugin_for_its_memory(monkeypatch):
    """``dask scheduler --preload packings.service.dashboard`` (a scheduler of many machines, also when it is
    started again) gives it :class:`packings.service.plugin.TaskLeftovers` itself."""
    import packings.service.dashboard
    import packings.service.plugin

    added = {}

    class Scheduler:
        http_application = type("App", (), {"add_handlers": lambda *a: None})()

        def add_plugin(self, plugin):
            added[plugin.name] = plugin

    monkeypatch.delenv("PACKINGS_DB", raising=False)
    packings.service.dashboard.dask_setup(Scheduler())
    assert isinstance(added.get(packings.service.plugin.TaskLeftovers.name), packings.service.plugin.TaskLeftovers)


def _sigint_by_default() -> None:
    """In the child before exec: SIGINT back to its default action, for a terminal's Ctrl-C to reach
    it even when the tests run in the background (a shell starts background jobs with SIGINT ignored,
    and Python leaves an ignored SIGINT ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_is_one_line_and_exit_130_and_the_run_resumes(db_url, reference10):
    """Ctrl-C in a terminal signals the whole process group (the coordinator and its local workers):
    one line, exit status 130, no worker's traceback, leases put back; the same command resumes.
    n = 10 (about 10 s of expansions on two workers), so that the signal lands mid-run: an n = 9 run
    can finish in the moment between the test seeing its fifth expansion done and the signal."""
    import os

    proc = subprocess.Popen(
        [sys.executable, "-m", "packings.service.cli", "enumerate", "10", "--db", db_url, "--workers", "2", "--quiet"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=_sigint_by_default,
    )
    try:
        wait_for(lambda: done_count(db_url) >= 5, proc)
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 130, (out, err)
    lines = err.splitlines()
    assert lines[-1] == "packings: interrupted; run the same command to resume" and "Traceback" not in err, err
    assert all(line.startswith("packings: compiling the numerical kernels") for line in lines[:-1]), err
    [run] = json.loads(packings("status", "--json", "--db", db_url).stdout)
    assert run["status"] == "interrupted" and run["leased"] == 0 and run["done"] < 263, run
    r = packings("enumerate", "10", "--db", db_url, "--workers", "2", "--quiet")
    assert r.returncode == 0, r.stderr
    assert "n = 10: 263 rigid clusters" in r.stdout and "(resumed)" in r.stdout
    assert_same_clusters(db_url, 10, reference10)


def test_sigterm_stops_a_run_as_ctrl_c_does_with_exit_143(db_url):
    """SIGTERM to the coordinator alone (as docker compose stop or systemd send it): one line, exit
    status 143, no traceback, the run interrupted with its leases put back, its workers gone."""
    import psutil

    proc = start("enumerate", "10", "--db", db_url, "--workers", "2", "--quiet")
    try:
        wait_for(lambda: done_count(db_url) >= 5, proc)
        workers = worker_processes(proc.pid)
        assert workers
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 143, (out, err)
    lines = err.splitlines()
    assert lines[-1] == "packings: terminated (SIGTERM); run the same command to resume" and "Traceback" not in err, err
    [run] = json.loads(packings("status", "--json", "--db", db_url).stdout)
    assert run["status"] == "interrupted" and run["leased"] == 0 and run["done"] < 263, run
    gone, alive = psutil.wait_procs(workers, timeout=30)
    assert alive == []


@pytest.mark.slow
def test_a_run_restricted_to_many_contacts_finds_the_papers_clusters_with_that_many(paper_counts, tmp_path):
    """`enumerate 11 --min-contacts 28 --max-break 3` (a ground-state run: M(11) - 1, seeded from a
    close-packed fragment with 28 contacts) finds the paper's 20 clusters with 28 contacts and the one
    with 29, and nothing with fewer."""
    url = f"sqlite:///{tmp_path / 'g.db'}"
    r = packings(
        "enumerate",
        "11",
        "--min-contacts",
        "28",
        "--max-break",
        "3",
        "--db",
        url,
        "--workers",
        "2",
        "--json",
        "--quiet",
    )
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    want = {m: c for m, c in paper_counts["clusters_by_contacts"]["11"].items() if int(m) >= 28}
    assert out["status"] == "complete" and out["by_contacts"] == want == {"28": 20, "29": 1}


@pytest.mark.slow
def test_enumerate_gives_the_papers_count_of_11(paper_counts, tmp_path):
    """`enumerate 11`, glued by default, in one command: the paths reach 1658 clusters, the glued pass adds
    the one no path reaches (26 contacts, hcp), its expansion finds nothing more, and the catalogue is the
    paper's 1659, contact by contact.  Rerun, it makes no pass and prints the same."""
    url = f"sqlite:///{tmp_path / 'g.db'}"
    r = packings("enumerate", "11", "--db", url, "--workers", "2", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["status"] == "complete" and out["by_contacts"] == paper_counts["clusters_by_contacts"]["11"]
    assert sum(out["by_contacts"].values()) == 1659
    [p] = out["catalysis"]
    assert [(f["contacts"], f["lattice"]) for f in p["new"]] == [(26, "hcp")] and p["expansions_added"] == 1
    again = json.loads(packings("enumerate", "11", "--db", url, "--json", "--quiet").stdout)
    assert again["catalysis"] == [] and again["by_contacts"] == out["by_contacts"]
    stats = packings("stats", "--n", "11", "--db", url)
    assert stats.returncode == 0 and "as the paper at every number of contacts" in stats.stdout, stats.stdout
