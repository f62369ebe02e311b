"""``packings enumerate N --slurm``: the workers as Slurm batch jobs (dask-jobqueue's SLURMCluster), on a
real single-node Slurm: munged, slurmctld and slurmd on this machine (tests/slurm/start-slurm.sh, which
.ci/run runs; this module runs it itself where Slurm is installed but not started and it may).

Without Slurm (or dask-jobqueue) the tests that need it skip, saying why; where the environment variable
CI is set they fail instead.  The options' checks need neither.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from sqlalchemy import select, text

from packings.service import slurm as slurm_module
from packings.service.db import make_engine, sessions
from packings.service.models import DONE, ExpansionRow
from packings.service.slurm import JOB_GONE_SECONDS, JOB_NAME, JobKeeper
from tests.helpers import SURFACE_KILLS, done_count, wait_for
from tests.helpers import packings as cli

START_SLURM = Path(__file__).resolve().parents[1] / "slurm" / "start-slurm.sh"
DEADLINE = 900.0  #: seconds a run on Slurm may take before the test gives up (the kernels may compile first)


def _controller_answers() -> bool:
    r = subprocess.run(["scontrol", "ping"], capture_output=True, text=True, timeout=30)
    return r.returncode == 0 and "UP" in r.stdout


def _slurm_problem() -> str | None:
    """None if this machine has a Slurm to submit to (started now if it can be), else why not."""
    try:
        import dask_jobqueue  # noqa: F401
    except ImportError:
        return "dask-jobqueue is not installed: pip install 'packings[slurm]'"
    if shutil.which("sbatch") is None:
        return "no Slurm here (sbatch not found): apt-get install slurm-wlm munge, then tests/slurm/start-slurm.sh"
    if _controller_answers():
        return None
    if os.geteuid() == 0 and shutil.which("slurmctld"):
        r = subprocess.run(["bash", str(START_SLURM)], capture_output=True, text=True, timeout=180)
        if r.returncode == 0 and _controller_answers():
            return None
        return f"tests/slurm/start-slurm.sh could not start Slurm: {(r.stderr or r.stdout).strip()[-300:]}"
    return "Slurm's controller does not answer (scontrol ping): run tests/slurm/start-slurm.sh as root"


@pytest.fixture
def slurm():
    """A Slurm to submit to, with none of packings' worker jobs in it, before the test and after it (a
    failed test's jobs are cancelled, so that they do not hold the node's cores for the next one)."""
    problem = _slurm_problem()
    if problem:
        if os.environ.get("CI"):
            pytest.fail(f"CI needs Slurm for these tests: {problem}")
        pytest.skip(problem)
    _no_jobs_of_ours("packings' worker jobs of an earlier run to leave Slurm")
    yield
    _no_jobs_of_ours("packings' worker jobs of the test to leave Slurm")


def _no_jobs_of_ours(what: str) -> None:
    """Cancel packings' worker jobs, if any, and wait until Slurm holds none."""
    if _our_jobs():
        subprocess.run(["scancel", "-n", JOB_NAME], capture_output=True, timeout=30)
    wait_for(lambda: not _our_jobs(), None, timeout=120, interval=0.2, what=what, explain=_queue)


def _queue() -> str:
    """Slurm's queue, every job and state, for a failure's message."""
    r = subprocess.run(["squeue", "-a", "-t", "all", "-o", "%i %j %T %r %M"], capture_output=True, text=True)
    return "squeue: " + " | ".join(r.stdout.strip().splitlines())


def _our_jobs() -> dict[str, str]:
    """packings' worker jobs that Slurm holds: job id -> state (PENDING, RUNNING, COMPLETING, ...)."""
    r = subprocess.run(["squeue", "-h", "-n", JOB_NAME, "-o", "%i %T"], capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    return dict(line.split() for line in r.stdout.splitlines() if line.strip())


def _running() -> set[str]:
    return {job for job, state in _our_jobs().items() if state == "RUNNING"}


def _workers_of_jobs(folder: Path) -> dict[str, str]:
    """Dask worker address -> the Slurm job it ran in, from the jobs' output (slurm-<job id>.out in the
    folder they were submitted from), where each worker says where it started."""
    out = {}
    for log in folder.glob("slurm-*.out"):
        job = log.stem.removeprefix("slurm-")
        for address in re.findall(r"Start worker at:\s+(\S+)", log.read_text(errors="replace")):
            out[address] = job
    return out


def _expansions_by_worker(url: str) -> dict[str, int]:
    engine = make_engine(url)
    try:
        with sessions(engine)() as s:
            rows = s.execute(select(ExpansionRow.worker).where(ExpansionRow.status == DONE)).scalars().all()
    finally:
        engine.dispose()
    counts: dict[str, int] = {}
    for w in rows:
        counts[w] = counts.get(w, 0) + 1
    return counts


def _start(folder: Path, *args, env=None):
    """``packings`` in ``folder`` (where Slurm writes its jobs' output), its output piped."""
    return subprocess.Popen(
        [sys.executable, "-m", "packings.service.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=folder,
        env={**os.environ, **(env or {})},
    )


def _assert_the_papers_n10(out: str, url: str, paper_counts) -> dict:
    """The run's --json says complete, with the paper's clusters of 10 by number of contacts (263 in all),
    and nothing is left failed or leased; returns the run's line of `packings status --json`."""
    result = json.loads(out)
    assert result["status"] == "complete" and result["total"] == 263
    assert result["by_contacts"] == paper_counts["clusters_by_contacts"]["10"]
    r = cli("status", "--json", "--db", url)
    [run] = json.loads(r.stdout)
    assert run["failed"] == 0 and run["leased"] == 0 and run["pending"] == 0
    return run


# --------------------------------------------------------------------------- the options, checked first


@pytest.mark.parametrize(
    "args, says",
    [
        (["--slurm", "--workers", "2"], "--slurm starts its own workers: not with --workers or --scheduler"),
        (["--slurm", "--scheduler", "tcp://127.0.0.1:1"], "not with --workers or --scheduler"),
        (["--jobs", "2", "--cores", "4"], "--jobs, --cores only with --slurm"),
        (["--slurm", "--walltime", "soon"], "slurm walltime must be a Slurm time such as 02:00:00"),
        (["--slurm", "--memory", "lots"], "slurm memory must be an amount such as 4GB"),
        (["--slurm", "--jobs", "0"], "Invalid value for '--jobs'"),
        (["--slurm"], "--slurm needs a PostgreSQL database that the batch jobs reach"),
    ],
)
def test_bad_slurm_options_are_one_line_before_anything_starts(tmp_path, args, says):
    db = tmp_path / "packings.db"
    r = cli("enumerate", "9", "--db", f"sqlite:///{db}", *args)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    [line] = r.stderr.strip().splitlines()
    assert line.startswith("packings: error: ") and says in line, line
    assert not db.exists()  # no database made, and no job submitted (nothing got that far)


def test_the_python_api_checks_the_slurm_options_too(tmp_path):
    import packings
    from packings.service.errors import UsageError

    url = f"sqlite:///{tmp_path / 'packings.db'}"
    with pytest.raises(UsageError, match="cores must be between 1 and 1024"):
        packings.enumerate(9, url, slurm={"cores": 0})
    with pytest.raises(UsageError, match="slurm processes is the number of cores"):
        packings.enumerate(9, url, slurm={"cores": 4, "processes": 2})
    with pytest.raises(UsageError, match="needs a PostgreSQL database"):
        packings.enumerate(9, url, slurm={"jobs": 2})
    assert not (tmp_path / "packings.db").exists()


def test_no_slurm_on_the_machine_is_one_line(pg_url, tmp_path):
    """--slurm where sbatch is not on the PATH: one line, nothing started."""
    env = {**os.environ, "PATH": str(Path(sys.executable).parent)}
    r = cli("enumerate", "9", "--db", pg_url, "--slurm", "--quiet", cwd=tmp_path, env=env)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    [line] = r.stderr.strip().splitlines()
    assert (
        line == "packings: error: --slurm needs Slurm's commands (sbatch, scancel) on this machine's PATH: none found"
    )


def test_a_partition_slurm_does_not_have_is_one_line(slurm, pg_url, tmp_path):
    """Slurm is asked (sbatch --test-only) before any job is submitted."""
    r = cli("enumerate", "9", "--db", pg_url, "--slurm", "--queue", "no-such-partition", "--quiet", cwd=tmp_path)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("packings: error: Slurm refuses the worker jobs: ") and "partition" in last, last
    assert not _our_jobs()


# --------------------------------------------------------------------------- the job keeper, on its own


class _Job:
    def __init__(self, job_id):
        self.job_id, self.closed = job_id, False

    async def close(self):
        self.closed = True


class _Cluster:
    """What :class:`JobKeeper` reads of a SLURMCluster: its jobs (spec and started), the scheduler's
    workers by name, ``sync`` and ``scale``."""

    def __init__(self, jobs: dict[str, str]):
        self.worker_spec = {name: {} for name in jobs}
        self.workers = {name: _Job(job_id) for name, job_id in jobs.items()}
        self.scheduler = SimpleNamespace(workers={})
        self.scaled: list[int] = []

    def sync(self, f, *args):
        return asyncio.run(f(*args))

    def scale(self, jobs):
        self.scaled.append(jobs)

    def join(self, *names):
        self.scheduler.workers = {f"tcp://{w}": SimpleNamespace(name=w) for w in names}


def test_the_keeper_replaces_a_job_that_ended_before_its_workers_joined(monkeypatch, caplog):
    """A job cancelled (or failed) before its worker joined is replaced once Slurm says it has ended or
    forgets it; jobs pending or running whose workers have not joined are left to wait, and so is every
    job while squeue does not answer.  Slurm is asked at most every JOB_GONE_SECONDS."""
    clock = [1000.0]
    monkeypatch.setattr(slurm_module.time, "monotonic", lambda: clock[0])
    states = {"11": "CANCELLED", "12": "RUNNING", "13": "PENDING"}
    asked: list[list[str]] = []

    def squeue(ids):
        asked.append(ids)
        return None if states is None else {k: v for k, v in states.items() if k in ids}

    cluster = _Cluster({"a": "11", "b": "12", "c": "13", "d": "14"})  # 14: forgotten by Slurm
    keeper = JobKeeper(cluster, 4, states=squeue)
    with caplog.at_level(logging.WARNING, logger="packings"):
        assert keeper() == 2
    assert asked == [["11", "12", "13", "14"]]
    assert set(cluster.worker_spec) == {"b", "c"} and cluster.scaled == [4]
    assert "Slurm job 11 (a) has lost its workers: submitting another in its place" in caplog.text
    assert "Slurm job 14 (d) has lost its workers" in caplog.text
    states["12"] = "FAILED"
    assert keeper() == 0 and len(asked) == 1  # not asked again before JOB_GONE_SECONDS
    clock[0] += JOB_GONE_SECONDS
    states = None  # squeue does not answer: nothing is replaced
    assert keeper() == 0 and set(cluster.worker_spec) == {"b", "c"}
    clock[0] += JOB_GONE_SECONDS
    states = {"12": "FAILED", "13": "RUNNING"}
    assert keeper() == 1 and set(cluster.worker_spec) == {"c"} and cluster.scaled == [4, 4]


def test_the_keeper_replaces_a_job_whose_workers_left(monkeypatch):
    """A job whose workers had joined is replaced (and cancelled) once none of them has been there for
    JOB_GONE_SECONDS, Slurm not asked once every job's workers have joined; a worker back in time keeps
    its job."""
    clock = [0.0]
    monkeypatch.setattr(slurm_module.time, "monotonic", lambda: clock[0])
    cluster = _Cluster({"a": "21", "b": "22"})
    asked: list[list[str]] = []
    keeper = JobKeeper(cluster, 2, states=lambda ids: asked.append(ids) or {i: "RUNNING" for i in ids})
    cluster.join("a-0", "a-1", "b")  # a runs two worker processes
    assert keeper() == 0 and keeper.joined == {"a", "b"}
    cluster.join("b")
    assert keeper() == 0
    clock[0] += JOB_GONE_SECONDS / 2
    cluster.join("a-1", "b")  # one of a's processes back: a is kept
    assert keeper() == 0
    cluster.join("b")
    assert keeper() == 0
    clock[0] += JOB_GONE_SECONDS
    job_a = cluster.workers["a"]
    assert keeper() == 1 and set(cluster.worker_spec) == {"b"} and job_a.closed and cluster.scaled == [2]
    assert asked == [["21", "22"]]  # at the first look only, before any worker had been seen


# --------------------------------------------------------------------------- runs on Slurm


@pytest.mark.slow
def test_enumerate_10_with_its_workers_as_slurm_jobs(slurm, pg_url, paper_counts, tmp_path):
    """n = 10 with --slurm --jobs 2 --cores 1: two worker jobs run (squeue shows them), every expansion is
    done by a worker of one of them, the run finds the 263 clusters, and its jobs leave Slurm with it."""
    proc = _start(
        tmp_path, "enumerate", "10", "--db", pg_url, "--slurm", "--jobs", "2", "--cores", "1", "--json", "--quiet"
    )
    seen: set[str] = set()
    try:
        deadline = time.monotonic() + DEADLINE
        while proc.poll() is None and time.monotonic() < deadline:
            seen |= _running()
            time.sleep(0.2)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    _assert_the_papers_n10(out, pg_url, paper_counts)
    assert len(seen) == 2
    wait_for(lambda: not _our_jobs(), None, timeout=60, interval=0.2, what="end of the run's jobs")
    jobs_of = _workers_of_jobs(tmp_path)
    by_worker = _expansions_by_worker(pg_url)
    assert sum(by_worker.values()) == 263
    assert set(by_worker) <= set(jobs_of), "an expansion done outside the Slurm jobs"
    assert {jobs_of[w] for w in by_worker} <= seen


@pytest.mark.slow
def test_a_cancelled_job_loses_nothing_and_is_replaced(slurm, pg_url, paper_counts, tmp_path):
    """scancel one of the two worker jobs once some expansions are done: the tasks lost with it reach the
    coordinator (allowed-failures 0), which puts their expansions back (retries); another job is submitted
    in its place; once its worker has joined the other first job is cancelled too, so that the rest of
    the run is the replacement's.  The run completes with the 263 clusters, nothing failed or left leased,
    and the lost job and its worker are each said in one line."""
    proc = _start(
        tmp_path,
        "enumerate",
        "10",
        "--db",
        pg_url,
        "--slurm",
        "--jobs",
        "2",
        "--cores",
        "1",
        "--json",
        "--quiet",
        env=SURFACE_KILLS,
    )
    try:
        first = wait_for(
            lambda: len(_running()) == 2 and _running(), proc, timeout=DEADLINE, interval=0.2, what="two running jobs"
        )
        wait_for(
            lambda: set(_workers_of_jobs(tmp_path).values()) >= first,
            proc,
            timeout=DEADLINE,
            interval=0.2,
            what="both jobs' workers started",
        )
        wait_for(lambda: done_count(pg_url) >= 20, proc, timeout=DEADLINE, interval=0.2, what="20 expansions done")
        victim, other = sorted(first)
        # the run held (the expansions table locked) until the replacement's worker has joined: on a quiet
        # machine the other job would otherwise finish the run before the lost one's 10 s are up, or before
        # the replacement's worker starts
        engine = make_engine(pg_url)
        try:
            with engine.connect() as conn:  # a transaction, holding the lock until it is rolled back
                conn.execute(text("LOCK TABLE expansions IN ACCESS EXCLUSIVE MODE"))
                done_before = conn.execute(text("SELECT count(*) FROM expansions WHERE status = 'done'")).scalar()
                subprocess.run(["scancel", victim], check=True)
                replacement = wait_for(
                    lambda: set(_running()) - first,
                    proc,
                    timeout=120,
                    interval=0.2,
                    what="replacement job",
                    explain=_queue,
                ).pop()
                wait_for(
                    lambda: replacement in set(_workers_of_jobs(tmp_path).values()),
                    proc,
                    timeout=120,
                    interval=0.2,
                    what="replacement's worker",
                    explain=_queue,
                )
                conn.rollback()
        finally:
            engine.dispose()
        subprocess.run(["scancel", other], check=True)
        out, err = proc.communicate(timeout=DEADLINE)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    run = _assert_the_papers_n10(out, pg_url, paper_counts)
    assert run["retries"] > 0 and done_before < 263
    assert re.search(rf"Slurm job {victim} \(\S+\) has lost its workers: submitting another in its place", err), err
    assert re.search(r"run \d+: 1 Dask worker\(s\) left \(tcp://", err), err
    jobs_of = _workers_of_jobs(tmp_path)
    by_job: dict[str, int] = {}
    for worker, k in _expansions_by_worker(pg_url).items():
        by_job[jobs_of[worker]] = by_job.get(jobs_of[worker], 0) + k
    assert by_job.get(replacement, 0) > 0, by_job  # a late joiner got the database plugin and did work
    wait_for(lambda: not _our_jobs(), None, timeout=60, interval=0.2, what="end of the run's jobs")


def _state(job: str) -> str:
    """The state Slurm gives ``job`` (RUNNING, TIMEOUT, ...; "" once it has forgotten it)."""
    r = subprocess.run(["squeue", "-h", "-t", "all", "-j", job, "-o", "%T"], capture_output=True, text=True, timeout=30)
    return r.stdout.strip()


@pytest.mark.slow
def test_a_job_past_its_walltime_is_replaced(slurm, pg_url, paper_counts, tmp_path):
    """n = 9 on one job of two cores (two worker processes) with a walltime of one minute.  Once its
    workers have done a few expansions the run is held (the expansions table locked) until Slurm has
    ended the job at its walltime (TIMEOUT), so that the limit falls mid-run however fast the machine:
    another job is submitted in its place, and the run completes in it with the paper's 52 clusters,
    nothing failed."""
    from sqlalchemy import text

    proc = _start(
        tmp_path,
        "enumerate",
        "9",
        "--db",
        pg_url,
        "--slurm",
        "--jobs",
        "1",
        "--cores",
        "2",
        "--walltime",
        "1",
        "--json",
        "--quiet",
    )
    engine = make_engine(pg_url)
    try:
        [first] = wait_for(_running, proc, timeout=DEADLINE, interval=0.2, what="a running job")
        wait_for(lambda: done_count(pg_url) >= 3, proc, timeout=DEADLINE, interval=0.2, what="3 expansions done")
        with engine.connect() as conn:  # a transaction, holding the lock until it is rolled back
            conn.execute(text("LOCK TABLE expansions IN ACCESS EXCLUSIVE MODE"))
            held = conn.execute(text("SELECT count(*) FROM expansions WHERE status = 'done'")).scalar()
            wait_for(
                lambda: _state(first) == "TIMEOUT",
                proc,
                timeout=180,
                interval=0.2,
                what="end of the first job at its walltime",
                explain=_queue,
            )
            replacement = wait_for(
                lambda: _running() - {first}, proc, timeout=120, interval=0.2, what="replacement job", explain=_queue
            ).pop()
            conn.rollback()
        out, err = proc.communicate(timeout=DEADLINE)
    finally:
        proc.kill()
        engine.dispose()
    assert proc.returncode == 0, err
    result = json.loads(out)
    assert result["status"] == "complete" and result["total"] == 52 and held < 52
    assert result["by_contacts"] == paper_counts["clusters_by_contacts"]["9"]
    [run] = json.loads(cli("status", "--json", "--db", pg_url).stdout)
    assert run["failed"] == 0 and run["leased"] == 0 and run["pending"] == 0
    assert re.search(rf"Slurm job {first} \(\S+\) has lost its workers: submitting another in its place", err), err
    jobs_of = _workers_of_jobs(tmp_path)
    assert any(jobs_of[w] == replacement for w in _expansions_by_worker(pg_url)), "the replacement did nothing"
    wait_for(lambda: not _our_jobs(), None, timeout=60, interval=0.2, what="end of the run's jobs")


@pytest.mark.slow
def test_the_recipe_with_a_slurm_cluster_of_ones_own(slurm, pg_url, paper_counts, tmp_path):
    """packings.enumerate's docstring recipe: a SLURMCluster made and scaled by the caller, given as
    ``scheduler``, with the preload; the run completes on its job, and the cluster is left as it was
    (its job still running: the caller closes it)."""
    import packings
    from packings.service.slurm import slurm_cluster_class

    SLURMCluster = slurm_cluster_class()
    with SLURMCluster(
        cores=1,
        processes=1,
        memory="1GB",
        walltime="00:10:00",
        job_name=JOB_NAME,
        log_directory=str(tmp_path),
        worker_extra_args=["--preload", "packings.service.plugin"],
        scheduler_options={"dashboard_address": "127.0.0.1:0"},
    ) as cluster:
        cluster.scale(jobs=1)
        result = packings.enumerate(9, pg_url, scheduler=cluster, progress=False)
        assert result.status == "complete" and result.total == 52
        assert result.by_contacts == {int(k): v for k, v in paper_counts["clusters_by_contacts"]["9"].items()}
        assert len(_running()) == 1 and len(cluster.scheduler.workers) == 1
    wait_for(lambda: not _our_jobs(), None, timeout=60, interval=0.2, what="end of the cluster's job")
