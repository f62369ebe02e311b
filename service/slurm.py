"""Dask workers as Slurm batch jobs: ``packings enumerate N --slurm`` (and ``packings.enumerate(...,
slurm={...})``), through dask-jobqueue's ``SLURMCluster`` (the extra ``packings[slurm]``).

The coordinator's process runs the Dask scheduler, as it does for a local cluster; each job runs
``dask worker`` with one single-threaded worker process per core it books (the numerics are
single-threaded), each of them loading the tasks' modules and the compiled kernels, warmed up, before
it joins (``--preload packings.service.plugin``: :func:`packings.service.plugin.dask_setup`).  The
database plugin (:class:`packings.service.plugin.DatabasePlugin`) is registered with the scheduler by
the coordinator, and so reaches every worker that joins, late or as a replacement.

A job that ends while the run goes on (``scancel``, its walltime, a node lost) is a fault like a killed
local worker: the coordinator puts back the expansions of the tasks that were lost with it, and
:class:`JobKeeper` submits another job in its place, so that the run keeps the jobs it asked for.

Loading this module is light (no Dask until a function runs).
"""

from __future__ import annotations

import logging
import re
import shutil
import signal
import subprocess
import tempfile
import threading
import time

from packings.service.errors import SchedulerError, UsageError
from packings.service.validate import check_range

log = logging.getLogger(__name__)

#: the options ``--slurm`` takes on the command line; ``slurm={...}`` takes these and any other keyword of
#: ``dask_jobqueue.SLURMCluster`` (account, job_extra_directives, local_directory, log_directory, python, ...)
OPTIONS = ("jobs", "cores", "memory", "queue", "walltime")
MEMORY_PER_CORE = 2  #: GiB booked per core (per worker process) when no memory is given
JOB_NAME = "packings-worker"  #: the jobs' name in squeue (``#SBATCH -J``)
#: how long a job whose workers had joined may be without any of them before it is replaced (its worker
#: processes' nanny restarts one that dies within a second or two; a job that ended has none for good).
#: Shorter than Dask's own ``distributed.deploy.lost-worker-timeout`` (15 s), after which SLURMCluster
#: forgets the job itself.
JOB_GONE_SECONDS = 10.0
#: the states of a job that has ended (squeue's %T); a job Slurm no longer knows has ended too
ENDED = frozenset(
    {"BOOT_FAIL", "CANCELLED", "COMPLETED", "DEADLINE", "FAILED", "NODE_FAIL", "OUT_OF_MEMORY", "PREEMPTED", "TIMEOUT"}
)
WALLTIME = re.compile(r"^(\d+-)?\d+(:\d+){0,2}$")  #: Slurm's time formats: M, M:S, H:M:S, D-H, D-H:M, D-H:M:S


def slurm_cluster_class():
    """dask-jobqueue's ``SLURMCluster`` (:class:`UsageError` if it is not installed).

    Importing dask-jobqueue sets a SIGINT handler of its own (its ``runner`` module's, which exits without
    a word): the one there before is put back, so that Ctrl-C stops a run as it does otherwise, its leases
    put back.  Only the main thread can do that, so the command line and :func:`packings.enumerate` import
    it here, in their thread, before anything starts."""
    main = threading.current_thread() is threading.main_thread()
    before = signal.getsignal(signal.SIGINT) if main else None
    try:
        from dask_jobqueue import SLURMCluster  # optional (packings[slurm]), and sets SIGINT: imported here
    except ImportError:
        raise UsageError("--slurm needs dask-jobqueue, which is not installed: pip install 'packings[slurm]'") from None
    finally:
        if before is not None:
            signal.signal(signal.SIGINT, before)
    return SLURMCluster


def check_options(slurm: dict) -> dict:
    """The options of a Slurm cluster, checked before anything starts (a bad one is a :class:`UsageError`):
    ``jobs`` (default 1), ``cores`` per job (default 1; as many worker processes, one thread each),
    ``memory`` per job (default :data:`MEMORY_PER_CORE` GiB a core), ``queue`` (the partition; default
    Slurm's), ``walltime`` (default dask-jobqueue's configuration, ``jobqueue.slurm.walltime``), and any
    other keyword of ``SLURMCluster``, passed on as it is."""
    if not isinstance(slurm, dict):
        raise UsageError(f"slurm must be a dict of SLURMCluster options (got {type(slurm).__name__})")
    slurm_cluster_class()  # installed, and imported in this thread
    out = dict(slurm)
    out.setdefault("jobs", 1)
    out.setdefault("cores", 1)
    check_range("jobs", out["jobs"])
    check_range("cores", out["cores"])
    if "processes" in out and out["processes"] != out["cores"]:
        raise UsageError("slurm processes is the number of cores (one single-threaded worker process each)")
    out["processes"] = out["cores"]
    if out.get("memory") is None:
        out["memory"] = f"{MEMORY_PER_CORE * out['cores']}GiB"
    else:
        from dask.utils import parse_bytes  # the command line's start-up loads no Dask

        try:
            if parse_bytes(out["memory"]) <= 0:
                raise ValueError
        except (ValueError, TypeError):
            raise UsageError(f"slurm memory must be an amount such as 4GB or 3.5GiB (got {out['memory']!r})") from None
    if out.get("walltime") is not None and not WALLTIME.match(str(out["walltime"])):
        raise UsageError(
            f"slurm walltime must be a Slurm time such as 02:00:00 or 1-00:00:00 (got {out['walltime']!r})"
        )
    for name in ("queue", "walltime"):
        if out.get(name) is None:
            out.pop(name, None)  # dask-jobqueue's configuration, else Slurm's default
    return out


def require_sbatch() -> None:
    """:class:`SchedulerError` unless Slurm's commands are on the PATH."""
    if shutil.which("sbatch") is None:
        raise SchedulerError("--slurm needs Slurm's commands (sbatch, scancel) on this machine's PATH: none found")


def _first_line(text: str) -> str:
    lines = [line.strip() for line in (text or "").splitlines() if line.strip()]
    return lines[0] if lines else ""


def start_cluster(options: dict, dashboard_address: str, prologue=()):
    """A ``SLURMCluster`` for ``options`` (:func:`check_options`'), its scheduler in this process serving
    the dashboard at ``dashboard_address``, its jobs' scripts running the shell lines ``prologue`` first
    (before the user's ``job_script_prologue``), its job script checked by ``sbatch --test-only`` (a queue,
    memory or walltime Slurm refuses is said here, in one line: :class:`SchedulerError`), and its jobs
    submitted."""
    SLURMCluster = slurm_cluster_class()
    kwargs = {k: v for k, v in options.items() if k != "jobs"}
    kwargs["worker_extra_args"] = ["--preload", "packings.service.plugin", *kwargs.get("worker_extra_args", ())]
    kwargs.setdefault("job_name", JOB_NAME)
    kwargs["job_script_prologue"] = [*prologue, *kwargs.get("job_script_prologue", ())]
    scheduler_options = dict(kwargs.pop("scheduler_options", None) or {})
    scheduler_options.setdefault("dashboard_address", dashboard_address)
    try:
        cluster = SLURMCluster(scheduler_options=scheduler_options, silence_logs=logging.CRITICAL, **kwargs)
    except (ValueError, TypeError) as e:
        raise UsageError(f"slurm: {_first_line(str(e))}") from None
    try:
        _test_submission(cluster.job_script())
        cluster.scale(jobs=options["jobs"])
    except BaseException:
        cluster.close()
        raise
    return cluster


def _test_submission(script: str) -> None:
    """Ask Slurm whether it would take the job ``script`` (``sbatch --test-only``: nothing is submitted);
    if not, its error is a :class:`SchedulerError`."""
    with tempfile.NamedTemporaryFile("w", suffix=".sh", prefix="packings-job-") as f:
        f.write(script)
        f.flush()
        try:
            r = subprocess.run(["sbatch", "--test-only", f.name], capture_output=True, text=True, timeout=60)
        except (OSError, subprocess.TimeoutExpired) as e:
            raise SchedulerError(f"sbatch --test-only failed: {e}") from None
    if r.returncode != 0:
        why = _first_line(r.stderr) or _first_line(r.stdout) or f"exit status {r.returncode}"
        raise SchedulerError(f"Slurm refuses the worker jobs: {why.removeprefix('sbatch: error: ')}")


def slurm_states(job_ids: list[str]) -> dict[str, str] | None:
    """The state (squeue's %T: PENDING, RUNNING, CANCELLED, ...) of each of ``job_ids`` that Slurm still
    holds, those it has forgotten left out; None if squeue does not answer."""
    try:
        r = subprocess.run(
            ["squeue", "-h", "-t", "all", "-j", ",".join(job_ids), "-o", "%i %T"],
            capture_output=True,
            text=True,
            timeout=30,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    if r.returncode != 0:  # every id unknown is an error of squeue's: all forgotten
        return {} if "Invalid job id" in r.stderr else None
    return dict(line.split()[:2] for line in r.stdout.splitlines() if len(line.split()) >= 2)


class JobKeeper:
    """Keeps a ``SLURMCluster``'s jobs: a job is replaced by a new one once it is lost, that is once

    - its workers had joined and have all been gone for :data:`JOB_GONE_SECONDS` (cancelled, past its
      walltime, its node lost); it is cancelled too, should Slurm still hold it; or
    - its workers never joined and Slurm says it has ended (cancelled or failed before they started) or
      no longer knows it, asked every :data:`JOB_GONE_SECONDS` while such a job remains.

    A job still waiting in the queue, or starting, is left to wait.

    Dask-jobqueue does not do this itself: its cluster forgets a lost job only if the job had one worker
    process (it looks the worker's name up among its jobs', and a job of several is named apart from
    its workers), and submits another only when asked to scale again."""

    def __init__(self, cluster, jobs: int, states=None):
        self.cluster, self.jobs = cluster, jobs
        self.states = states or slurm_states  #: job ids -> {job id: state} of those Slurm holds, or None
        self.joined: set[str] = set()  #: jobs whose workers have joined
        self.gone_since: dict[str, float] = {}  #: job -> when it was first seen without a worker
        self.asked = -float("inf")  #: when Slurm was last asked about the jobs not joined

    def __call__(self) -> int:
        """Replace the jobs lost (in the cluster's event loop); returns how many."""
        return self.cluster.sync(self._replace_lost, self._ended_before_joining())

    @staticmethod
    def _jobs_worker(job: str, worker: str) -> bool:
        """Whether ``worker`` (a Dask worker's name) is one of ``job``'s processes: ``job``, or
        ``job-i`` when it runs several."""
        return worker == job or worker.startswith(job + "-") and worker[len(job) + 1 :].isdigit()

    def _ended_before_joining(self) -> set[str]:
        """The jobs (by name) whose workers have not joined and that Slurm says have ended, asked at most
        every :data:`JOB_GONE_SECONDS` (in the caller's thread: squeue is not run in the event loop)."""
        now = time.monotonic()
        waiting = {
            name: getattr(self.cluster.workers.get(name), "job_id", None)
            for name in list(self.cluster.worker_spec)
            if name not in self.joined
        }
        waiting = {name: job for name, job in waiting.items() if job}
        if not waiting or now - self.asked < JOB_GONE_SECONDS:
            return set()
        self.asked = now
        held = self.states(sorted(set(waiting.values())))
        if held is None:  # Slurm did not answer: ask again next time
            return set()
        return {name for name, job in waiting.items() if job not in held or held[job] in ENDED}

    async def _replace_lost(self, ended: set[str] = frozenset()) -> int:
        now = time.monotonic()
        present = [str(ws.name) for ws in self.cluster.scheduler.workers.values()]
        lost = []
        for name in list(self.cluster.worker_spec):
            if any(self._jobs_worker(name, w) for w in present):
                self.joined.add(name)
                self.gone_since.pop(name, None)
            elif name in self.joined and now - self.gone_since.setdefault(name, now) >= JOB_GONE_SECONDS:
                lost.append(name)
            elif name not in self.joined and name in ended:
                lost.append(name)
        for name in lost:
            self.cluster.worker_spec.pop(name, None)
            self.joined.discard(name)
            self.gone_since.pop(name, None)
            job = self.cluster.workers.pop(name, None)
            log.warning(
                "Slurm job %s (%s) has lost its workers: submitting another in its place",
                getattr(job, "job_id", None) or "?",
                name,
            )
            if job is not None:
                try:
                    await job.close()  # scancel, should Slurm still hold it
                except Exception:  # noqa: BLE001 - gone already
                    pass
        if lost:
            self.cluster.scale(jobs=self.jobs)
        return len(lost)
