"""The Dask side of ``packings enumerate``: the fork server that a local cluster's
worker processes are forked from, and the connection to a local cluster, to workers
in Slurm batch jobs (:mod:`packings.service.slurm`) or to an existing cluster, made
in the background while the caller opens the database.

Loading this module is light (no Dask, SQLAlchemy or numpy until a function runs):
the command line imports it before it starts the fork server.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

from packings.service.errors import SchedulerError
from packings.service.slurm import JobKeeper, start_cluster

# multiprocessing, Dask, YAML, the plugins (Dask, SQLAlchemy) and the dashboard (Bokeh; importing it adds
# its page to the schedulers started after) are imported by the functions that use them: the command line
# loads this module (every command, not only those that start a cluster) before it starts the fork server.

#: the modules that the fork server of a local cluster's workers loads before it forks them
FORK_SERVER_PRELOAD = ("distributed", "packings.service.preload")
#: setting this environment variable (spawn, fork, forkserver) chooses how Dask starts local workers
METHOD_ENV = "DASK_DISTRIBUTED__WORKER__MULTIPROCESSING_METHOD"


def start_fork_server() -> bool:
    """Start the process that a local cluster's worker processes are forked from; returns whether they
    will be (it may have been started already: then this does nothing more).

    It starts at once and loads, in the background, what every worker needs (:mod:`packings.service.preload`:
    Dask, SQLAlchemy, the numerical code, the compiled kernels, warmed up) once, while this process
    checks and opens the database and starts the scheduler.  Each worker forked from it joins within a
    few hundredths of a second of being asked for, where a worker spawned afresh (Dask's default)
    imports and loads all of it itself: 1.3 s of CPU per worker, on cores the command's own start-up
    needs too.

    Dask's environment for new worker processes (``distributed.nanny.pre-spawn-environ``: one BLAS
    thread, ``MALLOC_TRIM_THRESHOLD_``, and the hash seed that its nanny sets) is set before the server
    starts, so that the forked workers have it as spawned ones would.  Nothing is done where the
    platform has no fork server, nor when the user chose another start method (:data:`METHOD_ENV`, or
    ``distributed.worker.multiprocessing-method`` in Dask's configuration).
    """
    import multiprocessing
    from multiprocessing import forkserver

    refuse_while_importing_main()
    mark_unguarded()  # before the fork server starts: it and the workers forked from it inherit it
    import dask

    _load_distributed_defaults()
    method = dask.config.get("distributed.worker.multiprocessing-method")
    chosen = METHOD_ENV in os.environ or method != "spawn"
    if (chosen and method != "forkserver") or "forkserver" not in multiprocessing.get_all_start_methods():
        return False
    env = {k: str(v) for k, v in (dask.config.get("distributed.nanny.pre-spawn-environ") or {}).items()}
    if env.get("PYTHONHASHSEED") in (None, "0"):
        env["PYTHONHASHSEED"] = "6640"  # as Dask's nanny does, so that every worker hashes alike
    os.environ.update(env)
    multiprocessing.set_forkserver_preload(list(FORK_SERVER_PRELOAD))  # if it is not running yet
    forkserver.ensure_running()  # starts it (if need be) and returns; a worker's start waits for its preload
    dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"})
    return True


#: why the worker processes of a local cluster ended as they started (:func:`refuse_while_importing_main`)
UNGUARDED = (
    "its worker processes ran the script that starts it, which calls packings.enumerate at its top "
    'level: call it under `if __name__ == "__main__":`'
)
#: the file a worker process that ran its parent's script creates, for its parent to say why in one line
UNGUARDED_MARK_ENV = "PACKINGS_UNGUARDED_MARK"


def refuse_while_importing_main() -> None:
    """End this process (exit status 1) if it is a new process importing the main module of the one that
    started it.

    Every start method but fork has a new process (a local cluster's workers among them) import its
    parent's main module before it runs: a script that calls ``packings.enumerate`` at its top level,
    outside ``if __name__ == "__main__":``, calls it again in each worker as it starts.  There
    multiprocessing would refuse to start the fork server with a traceback of its own in every worker,
    each start of the cluster.  Instead the worker ends without writing anything and without a word,
    having created the file its parent named in :data:`UNGUARDED_MARK_ENV` (:func:`mark_unguarded`):
    the parent, whose local cluster then fails to start, finds it and says why once
    (:data:`UNGUARDED`), rather than each worker at each of its tries.  A parent that named no file
    (not this version of packings) gets the reason from the worker, as one line.  Python marks a
    process in that state as ``_inheriting``, which its own check reads too."""
    import multiprocessing

    if getattr(multiprocessing.current_process(), "_inheriting", False):
        mark = os.environ.get(UNGUARDED_MARK_ENV)
        if mark:
            try:
                Path(mark).touch()
            except OSError:
                mark = None
        if not mark:
            print(
                f"packings: error: a worker process of a local cluster ended: {UNGUARDED}", file=sys.stderr, flush=True
            )
        raise SystemExit(1)


def mark_unguarded() -> None:
    """Name the file that this process's new processes create if they run its script's call of
    ``packings.enumerate`` again (:func:`refuse_while_importing_main`): one per process, named in its
    environment, which they inherit (a fork server's from when it starts)."""
    mark = os.path.join(tempfile.gettempdir(), f"packings-unguarded-{os.getpid()}")
    if os.environ.get(UNGUARDED_MARK_ENV) != mark:  # not yet, or this process's parent's
        os.environ[UNGUARDED_MARK_ENV] = mark
        _ran_unguarded()  # an earlier process's with the same id: taken away


def _quiet_dask() -> None:
    """Dask's own logs of a failed or lost task ("Compute Failed" with the whole error, "marked as failed
    because workers died") would repeat what the coordinator logs in one line and keeps in the database:
    only Dask's critical messages are shown.  Dask gives some of its loggers levels of their own
    (distributed.client: warning, whose "Failed to reconnect to scheduler" came before the coordinator's one
    line when the scheduler was lost): those too.  The length of Dask's low-level log is set as the Client,
    scheduler and their streams are made."""
    import dask

    quiet = ("distributed", "bokeh", "tornado")
    below = tuple(f"{name}." for name in quiet)
    for name in [*quiet, *(k for k in list(logging.root.manager.loggerDict) if k.startswith(below))]:
        logging.getLogger(name).setLevel(logging.CRITICAL)
    if LOG_LENGTH_ENV not in os.environ:
        dask.config.set({"distributed.admin.low-level-log-length": LOG_LENGTH})


def _ran_unguarded() -> bool:
    """Whether the file this process named is there (a new process of it ran its script's call again);
    it is taken away (said once)."""
    mark = os.environ.get(UNGUARDED_MARK_ENV)
    if not mark:
        return False
    try:
        os.remove(mark)
    except FileNotFoundError:
        return False
    except OSError:  # there, but another's to remove
        pass
    return True


def _load_distributed_defaults() -> None:
    """Dask's configuration with distributed's defaults, as ``import distributed`` sets them, but without
    the import (0.3 s, which the fork server's start would wait for): from its ``distributed.yaml``."""
    import dask
    import yaml

    if "distributed" in sys.modules:
        return
    spec = importlib.util.find_spec("distributed")
    path = Path(spec.origin).with_name("distributed.yaml") if spec and spec.origin else None
    if path is None or not path.is_file():
        import distributed  # noqa: F401 - which sets them

        return
    dask.config.update_defaults(yaml.safe_load(path.read_text()))


#: setting this environment variable (True / False) decides whether local Dask workers profile their tasks
PROFILE_ENV = "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED"
#: setting this environment variable sets how many entries each of Dask's own logs keeps in this process
LOG_LENGTH_ENV = "DASK_DISTRIBUTED__ADMIN__LOW_LEVEL_LOG_LENGTH"
#: what the logs keep otherwise: Dask's default (1,000) keeps, for each stream of messages between the
#: client, the scheduler and a worker, the last 1,000 messages sent, every task's spec among them, so the
#: coordinator's process grows with each task submitted until they are full (docs/performance.md)
LOG_LENGTH = 100
DASHBOARD_ADDRESS = "127.0.0.1:8787"  #: where a local cluster serves its dashboard (another port if taken)
REVIVE_SECONDS = 15.0  #: how long a local worker slot may be without a process before it is replaced
START_ATTEMPTS = 3  #: tries to start the local cluster (a worker process that dies as it starts fails the start)
RECONNECT_SECONDS = 300.0  #: how long a coordinator tries to reach an existing scheduler again once it lost it
RECONNECT_ENV = "PACKINGS_RECONNECT_SECONDS"  #: overrides it
log = logging.getLogger(__name__)


class dask_client:
    """A Client on a new LocalCluster, on new Slurm jobs (``slurm``: the options of
    :func:`packings.service.slurm.check_options`), or on an existing cluster (``scheduler``: its
    scheduler's address, or a Dask cluster object of the caller's, e.g. a ``SLURMCluster``); errors
    become one line.

    The connection is made in the background from ``__enter__`` on, so that the caller can do its own
    work meanwhile (a local cluster takes a second or two: its scheduler and dashboard start, its worker
    processes are forked from the fork server (:func:`start_fork_server`) once that has loaded what they
    need, and run ``plugins``' setup before it is up; Slurm's jobs join whenever Slurm starts them, and
    get the plugins the coordinator registers then); :attr:`client` waits for it.
    """

    def __init__(
        self,
        scheduler,
        n_workers: int | None,
        quiet: bool,
        plugins=(),
        dashboard_address: str = DASHBOARD_ADDRESS,
        database: str | None = None,
        reconnect_seconds: float = RECONNECT_SECONDS,
        slurm: dict | None = None,
    ):
        self.scheduler, self.n_workers, self.quiet, self.plugins = scheduler, n_workers, quiet, tuple(plugins)
        self.dashboard_address, self.database = dashboard_address, database
        self.reconnect_seconds = reconnect_seconds
        self.slurm = slurm
        self._keeper = None  #: a Slurm cluster's :class:`packings.service.slurm.JobKeeper`
        self.cluster = self._client = self._error = self._thread = None
        self._announced = False
        self._dead_since: dict = {}  #: local worker slot -> when its process was first seen dead

    def __enter__(self) -> "dask_client":
        self._thread = threading.Thread(target=self._connect_or_fail, name="packings-dask-start", daemon=True)
        self._thread.start()
        return self

    def _connect_or_fail(self) -> None:
        try:
            self._connect()
        except BaseException as e:  # noqa: BLE001 - raised again by .client, in the caller's thread
            self._error = e

    def _connect(self) -> None:
        from distributed import Client

        _quiet_dask()
        if self.scheduler is not None and not isinstance(self.scheduler, str):  # the caller's cluster, as it is
            self._client = Client(self.scheduler)
        elif self.slurm is not None:
            self._client = self._slurm_client()
        elif self.scheduler:
            self._client = self._scheduler_client()
        else:
            self._client = self._local_client()
        self._bound_leftovers()

    def _slurm_client(self):
        """A Client of a new scheduler in this process whose workers are Slurm jobs, kept by a JobKeeper."""
        from distributed import Client

        import packings.service.dashboard

        warnings.filterwarnings("ignore", message=r"Port \d+ is already in use", category=UserWarning)
        # as a local cluster's workers, no statistical profiler unless asked (the variable, set, reaches the
        # jobs: sbatch passes this process's environment on)
        quiet_profile = [] if PROFILE_ENV in os.environ else [f"export {PROFILE_ENV}=False"]
        self.cluster = start_cluster(self.slurm, self.dashboard_address, prologue=quiet_profile)
        self._keeper = JobKeeper(self.cluster, self.slurm["jobs"])
        packings.service.dashboard.serve_json(self.cluster.scheduler)
        if self.database:
            packings.service.dashboard.watch(self.database)
        return Client(self.cluster)

    def _scheduler_client(self):
        """A Client of the existing scheduler at the address ``self.scheduler``, or SchedulerError in one line."""
        from distributed import Client

        try:
            client = Client(self.scheduler, timeout="10s")
        except (OSError, TimeoutError, ValueError) as e:
            raise SchedulerError(
                f"cannot reach the Dask scheduler at {self.scheduler}: "
                f"{str(e).splitlines()[0] if str(e) else type(e).__name__}"
            ) from None
        # A Client that loses its scheduler tries to connect again for as long as its timeout, then
        # closes: 10 s to connect at first (one that does not answer is said at once), then the
        # reconnection window (packings.service.coordinator waits for it and goes on)
        client._timeout = self.reconnect_seconds
        return client

    def _local_client(self):
        """A Client of a new local cluster of ``n_workers`` processes (one per core by default), forked from
        the fork server, with the packings page on its dashboard."""
        import dask
        from distributed import Client, LocalCluster

        from packings.service.plugin import LocalWorkerPlugin

        k = self.n_workers or os.cpu_count() or 1
        if PROFILE_ENV not in os.environ:
            # Dask's statistical profiler samples each worker's stack every 10 ms: 8 % of a run's time
            # at n = 11 (the dashboard's Profile page is empty without it; the variable turns it back on)
            dask.config.set({"distributed.worker.profile.enabled": False})
        start_fork_server()  # if `packings enumerate` has not yet
        # the plugins are set up in each worker process before it joins (later ones: client.register_plugin)
        import packings.service.dashboard  # its page joins the dashboard of the scheduler started now

        # a busy port: Dask takes another and warns; the address taken is said once, by .wait()
        warnings.filterwarnings("ignore", message=r"Port \d+ is already in use", category=UserWarning)
        for attempt in range(START_ATTEMPTS):
            try:
                self.cluster = LocalCluster(
                    n_workers=k,
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address=self.dashboard_address,
                    silence_logs=logging.CRITICAL,
                    plugins=(LocalWorkerPlugin(), *self.plugins),
                )
                break
            except RuntimeError as e:  # "Nanny failed to start": a worker process died while starting
                if _ran_unguarded():  # every try would end so
                    raise SchedulerError(f"the local Dask cluster failed to start: {UNGUARDED}") from None
                log.warning(
                    "the local Dask cluster failed to start (%s)%s",
                    e,
                    "; trying again" if attempt + 1 < START_ATTEMPTS else "",
                )
                if attempt + 1 == START_ATTEMPTS:
                    raise SchedulerError(f"the local Dask cluster failed to start: {e}") from None
        packings.service.dashboard.serve_json(self.cluster.scheduler)
        if self.database:
            packings.service.dashboard.watch(self.database, self.cluster.scheduler)
        return Client(self.cluster)

    def _bound_leftovers(self) -> None:
        """Give the scheduler :class:`packings.service.plugin.TaskLeftovers`, which keeps what it remembers of the
        run's tasks once they are gone bounded.  An existing scheduler that cannot load it (the package not
        installed beside it) runs on: its memory grows by a few hundred bytes a task, which is said once."""
        from packings.service.plugin import TaskLeftovers

        try:
            self._client.register_plugin(TaskLeftovers())
        except Exception as e:  # noqa: BLE001 - the run goes on; only the scheduler's memory is at stake
            log.warning(
                "the Dask scheduler did not take packings' plugin for its memory (%s): it keeps a few "
                "hundred bytes of each task; install packings beside it, or start it with "
                "--preload packings.service.dashboard",
                str(e).splitlines()[0] if str(e) else type(e).__name__,
            )

    def revive_workers(self) -> int:
        """Replace the local cluster's workers whose nanny gave up (a worker process killed while it
        was starting again leaves its nanny without one, for good): each slot without a live process
        for :data:`REVIVE_SECONDS` gets a new nanny and worker; or the Slurm jobs that were lost
        (:class:`packings.service.slurm.JobKeeper`).  Returns how many were replaced (0 for an existing
        cluster, whose workers are its operator's)."""
        if self._keeper is not None:
            return self._keeper()
        if self.cluster is None:
            return 0
        now = time.monotonic()
        dead = []
        for name, nanny in list(self.cluster.workers.items()):
            if getattr(nanny, "is_alive", lambda: True)():
                self._dead_since.pop(name, None)
            elif now - self._dead_since.setdefault(name, now) >= REVIVE_SECONDS:
                dead.append(name)
        for name in dead:
            nanny = self.cluster.workers.pop(name)
            self.cluster.worker_spec.pop(name, None)
            self._dead_since.pop(name, None)
            try:
                self.cluster.sync(nanny.close, timeout=10)
            except Exception:  # noqa: BLE001 - it had no process left; its port is freed with the cluster
                pass
        if dead:
            log.warning("%d local worker(s) could not be restarted by their nanny: starting new ones", len(dead))
            self.cluster.scale(len(self.cluster.worker_spec) + len(dead))
        return len(dead)

    def fresh_workers(self) -> bool:
        """Replace the local cluster's worker processes by new ones (forked from the fork server by their
        nannies: a second or two), so that what one phase of a command grew in them (a run's caches, the
        heap its expansions left) is not carried into the next, e.g. the glued pass after the paths.
        An existing cluster's workers are its operator's: left alone.  Returns whether they were replaced;
        a restart that fails is logged and the work goes on with the workers there are."""
        if self.cluster is None:
            return False
        client = self.wait()
        try:
            client.restart_workers(list(client.scheduler_info()["workers"]), timeout=120)
        except Exception as e:  # noqa: BLE001 - the work runs on the workers as they are: more memory, no loss
            log.warning("the local workers could not be restarted (%s): going on with them", e)
            return False
        return True

    @property
    def client(self):
        """The Client, once connected (waits); a failure to connect is raised here."""
        return self.wait()

    def wait(self):
        """:attr:`client`."""
        if self._thread.is_alive():
            self._thread.join()
        if self._error is not None:
            raise self._error
        if not (self.quiet or self._announced):
            if self.slurm is not None:
                jobs, cores = self.slurm["jobs"], self.slurm["cores"]
                where = f"{jobs} Slurm job(s) of {cores} worker process(es) each, joining as Slurm starts them"
            elif self.scheduler is not None and not isinstance(self.scheduler, str):
                where = f"{type(self.scheduler).__name__} at {getattr(self.scheduler, 'scheduler_address', '?')}"
            else:
                where = self.scheduler or f"local cluster, {len(self._client.nthreads())} worker processes"
            link = self._client.dashboard_link
            if self.cluster is not None:
                wanted = self.dashboard_address.rsplit(":", 1)[-1]
                port = str(self.cluster.scheduler.http_server.port)
                if wanted not in ("0", port):
                    print(f"packings: dashboard port {wanted} is taken; serving it on {port}", file=sys.stderr)
                link = link.replace("/status", "/packings")
            elif self._serves_page():
                link = link.replace("/status", "/packings")
            print(f"dask: {where}; dashboard {link}", file=sys.stderr, flush=True)
            self._announced = True
        return self._client

    def _serves_page(self) -> bool:
        """Whether the existing scheduler serves the packings page (started with ``--preload
        packings.service.dashboard``); False where it cannot say (packings not installed beside it)."""
        from packings.service.plugin import serves_page

        try:
            return bool(self._client.run_on_scheduler(serves_page))
        except Exception:  # noqa: BLE001 - Dask's own page is there in any case
            return False

    def __exit__(self, *exc):
        if self._thread is not None:
            self._thread.join()
        if self._client is not None:
            self._client.close()
        if self.cluster is not None:
            self.cluster.close()
        return False
