"""The run driver behind :func:`packings.enumerate` and ``packings enumerate``: check the request, start
the Dask cluster (local, Slurm jobs or an existing one) while the database is opened, drive the run
(:func:`packings.service.coordinator.run_enumeration`) and the glued catalysis passes after it
(:func:`packings.service.catalysis.catalyse`), with their progress bars.

Loading this module is light (no SQLAlchemy, numpy or Dask until a function runs): the command line
imports it (:func:`pass_bar`) before ``packings enumerate`` starts its workers' fork server.
"""

from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING, Callable

from packings.service.api import resolve_url
from packings.service.dask_cluster import (
    DASHBOARD_ADDRESS,
    RECONNECT_ENV,
    RECONNECT_SECONDS,
    dask_client,
    start_fork_server,
)
from packings.service.errors import UsageError
from packings.service.owners import busy
from packings.service.slurm import check_options, require_sbatch
from packings.service.validate import check_run
from packings.workers.kernel_cache import compile_apart, kernels_cached
from packings.workers.params import Params

if TYPE_CHECKING:
    from packings.service.coordinator import RunResult

# tqdm, SQLAlchemy and the modules that load it or numpy (the database, the worker plugin, the
# coordinator, the catalysis, the seeds) are imported by the functions that use them: the command line
# loads this module (pass_bar) before `packings enumerate` starts the fork server, and every 0.1 s of
# imports before it is 0.1 s more before the workers can start.


def _progress_bar(show: bool) -> Callable:
    """The expansions' bar, drawn from the run's first progress on (when its work starts: not while the
    cluster starts, whose lines would be written over it)."""
    from tqdm import tqdm

    bars = []

    def update(p):
        if not bars:
            bars.append(
                tqdm(total=0, unit="exp", desc="expansions", file=sys.stderr, disable=not show, dynamic_ncols=True)
            )
        bar = bars[0]
        bar.total = p.total
        bar.n = p.done
        bar.set_postfix_str(
            f"pending {p.pending + p.leased}, clusters {p.clusters}" + (f", failed {p.failed}" if p.failed else ""),
            refresh=False,
        )
        bar.refresh()

    update.close = lambda: bars and bars[0].close()  # type: ignore[attr-defined]
    return update


def _refuse_busy_run(engine, n: int, params) -> None:
    """Raise :class:`packings.service.owners.RunBusy` if a live coordinator holds the run for (n, params).  A
    text query on the runs table: neither the models nor the store are loaded before the cluster
    starts (the store's import alone takes half a second)."""
    from sqlalchemy import DateTime, Integer, String, column, text

    q = text("SELECT id, coordinator, heartbeat_at FROM runs WHERE n = :n AND params = :params").columns(
        column("id", Integer), column("coordinator", String), column("heartbeat_at", DateTime)
    )
    with engine.connect() as conn:
        row = conn.execute(q, {"n": n, "params": params.to_json()}).first()
    if row is not None and (held := busy(row.id, n, row.coordinator, row.heartbeat_at)) is not None:
        raise held


LOCAL_WORKERLESS_SECONDS = 60.0  #: a local cluster without a worker for this long ends the run (resumably)
WORKERLESS_ENV = "PACKINGS_WORKERLESS_SECONDS"  #: overrides it


def _seconds(variable: str, default: float) -> float:
    """A number of seconds from the environment ``variable``, else ``default``; a bad value is a UsageError."""
    value = os.environ.get(variable)
    try:
        seconds = default if value is None else float(value)
    except ValueError:
        seconds = -1.0
    if not seconds > 0:
        raise UsageError(f"{variable} must be a positive number of seconds (got {value!r})")
    return seconds


def timeouts(local: bool) -> tuple[float | None, float]:
    """How long the work waits without a Dask worker (``local``: a local cluster, which cannot start them
    again after that long, :data:`LOCAL_WORKERLESS_SECONDS`; an existing cluster's workers may join later,
    and Slurm's jobs may wait in its queue: None, it waits for them), and how long the Client tries to
    reach a lost scheduler again (:data:`packings.service.dask_cluster.RECONNECT_SECONDS`); each from
    the environment if set there, a bad value a UsageError."""
    workerless = _seconds(WORKERLESS_ENV, LOCAL_WORKERLESS_SECONDS) if local else None
    return workerless, _seconds(RECONNECT_ENV, RECONNECT_SECONDS)


def enumerate(
    n: int,
    url: str | None = None,
    *,
    workers: int | None = None,
    scheduler=None,
    slurm: dict | None = None,
    max_break: int | None = None,
    min_contacts: int | None = None,
    max_attempts: int = 3,
    progress: bool = True,
    dashboard_address: str = DASHBOARD_ADDRESS,
    glued: bool = True,
) -> RunResult:
    """Enumerate the rigid clusters of ``n`` spheres into the database at ``url`` (as
    :func:`packings.service.api.connect`; created if need be), or resume the run with the same n and
    parameters, and return its result: ``status`` ("complete" or "incomplete"), ``by_contacts``,
    ``total``, ``diagnostics``, ``seconds``, ``resumed``, ``errors``
    (:class:`packings.service.coordinator.RunResult`).

    The work runs on a new local Dask cluster of ``workers`` processes (default: one per core), on
    workers in new Slurm batch jobs (``slurm``, below), or on an existing cluster: ``scheduler`` is its
    scheduler's address (e.g. ``"tcp://host:8786"``) or a Dask cluster object of your own, which is used
    as it is (neither scaled nor closed).  ``max_break``
    caps the number of contacts broken at once (default: none); ``min_contacts`` keeps only clusters
    with at least that many contacts.  ``progress`` shows a progress bar on standard error.  A local
    cluster serves its Dask dashboard, with the run's own page (``/packings``, :mod:`packings.service.dashboard`),
    at ``dashboard_address`` (another port if that one is taken).

    With ``glued`` (the default), once the paths are done, a catalysis pass moves one sphere of every stored cluster
    of n onto each of its contact triangles (:func:`packings.service.catalysis.catalyse`, as ``packings catalyse
    N --glued``) and adds the rigid remainders no path reached; the run then expands them, and a pass over
    the clusters stored since follows, until one adds nothing (``catalysis``: the passes' reports).  A
    pass that ran to its end is recorded: the same call again makes none, unless clusters were stored
    since.  The paths alone miss a cluster at n = 11 and at n = 13; with the passes the catalogue is the
    paper's for every n <= 13 (docs/method.md).  ``glued=False`` follows the paths alone.

    ``slurm`` (needs ``pip install 'packings[slurm]'``, Slurm's commands and a PostgreSQL ``url`` that
    the batch jobs' nodes reach) runs the Dask scheduler in this process and the workers as Slurm
    jobs (dask-jobqueue's ``SLURMCluster``): ``dict(jobs=2, cores=8, memory="16GB", queue="compute",
    walltime="04:00:00")`` keeps two jobs of eight single-threaded worker processes each (defaults:
    one job, one core, 2 GiB a core; :func:`packings.service.slurm.check_options`); any other keyword
    of ``SLURMCluster`` (``account``, ``job_extra_directives``, ``log_directory``, ...) is passed on.  A
    job that ends before the run does (``scancel``, its walltime) is replaced, and the expansions its
    workers held are put back.  With a cluster of your own, give it the preload, so that each worker
    loads the numerical code before it joins (the database reaches it either way)::

        from dask_jobqueue import SLURMCluster
        import packings

        if __name__ == "__main__":
            with SLURMCluster(cores=8, processes=8, memory="16GB", walltime="04:00:00",
                              worker_extra_args=["--preload", "packings.service.plugin"]) as cluster:
                cluster.scale(jobs=2)
                packings.enumerate(12, "postgresql://user@db-host/packings", scheduler=cluster)

    (Its lost jobs are not replaced: that is what ``slurm=`` adds.)
    """
    local = scheduler is None and slurm is None
    slurm, params, url = _prepare(
        n, url, workers, scheduler, slurm, max_break, min_contacts, max_attempts, dashboard_address
    )
    workerless, reconnect = timeouts(local)
    from packings.service.db import open_database
    from packings.service.plugin import DatabasePlugin

    # a local cluster starts in the background, its workers warming up with the database plugin, while the
    # database is opened here; .client waits for it
    with dask_client(
        scheduler,
        workers,
        not progress,
        plugins=(DatabasePlugin(url),),
        dashboard_address=dashboard_address,
        database=url,
        reconnect_seconds=reconnect,
        slurm=slurm,
    ) as dask:
        if not local:
            dask.wait()  # an existing scheduler is reached (or that fails, in one line) before the database is touched
        engine = open_database(url, create=True)
        try:
            if scheduler is not None and engine.dialect.name == "sqlite":
                print(
                    "packings: warning: SQLite with a scheduler works only if every worker sees this file "
                    f"({engine.url.database}); use PostgreSQL for many machines",
                    file=sys.stderr,
                )
            return _paths_and_passes(engine, url, n, params, dask, progress, max_attempts, workerless, glued)
        finally:
            engine.dispose()


def _prepare(
    n: int,
    url: str | None,
    workers: int | None,
    scheduler,
    slurm: dict | None,
    max_break: int | None,
    min_contacts: int | None,
    max_attempts: int,
    dashboard_address: str,
) -> tuple[dict | None, Params, str]:
    """What :func:`enumerate` does before any Dask cluster starts: the request checked, the fork server of a
    local cluster started first thing, the database reached (a bad URL, server or schema, or a run another
    live coordinator holds, reported in one line) and the kernels' compilation announced.  Returns the
    checked Slurm options, the run's parameters and the database URL."""
    check_run(
        n,
        workers=workers,
        scheduler=scheduler,
        slurm=slurm is not None,
        max_break=max_break,
        max_attempts=max_attempts,
        dashboard_address=dashboard_address,
    )
    if slurm is not None:
        slurm = check_options(slurm)
    local = scheduler is None and slurm is None
    compiling = False
    if local or slurm is not None:
        compiling = kernels_cached() is False  # then the fork server (or this process, for Slurm) compiles them
    if local:
        start_fork_server()  # first: it loads what the local cluster's workers need while the database is opened
    params = Params(max_break=max_break, min_contacts=min_contacts)
    if min_contacts is not None:  # a run restricted so starts from a cluster with that many contacts
        from packings.workers.seeds import seed_cluster

        try:
            seed_cluster(n, params)
        except ValueError as e:
            raise UsageError(str(e)) from None
    url = resolve_url(url)
    if slurm is not None:
        _refuse_sqlite_for_slurm(url)
        require_sbatch()
    from packings.service.db import preflight

    preflight(url, check=lambda engine: _refuse_busy_run(engine, n, params))
    if compiling:  # said, rather than a silent minute
        print(
            "packings: compiling the numerical kernels, once for this installation (about a minute on two "
            "cores; later runs load them in a second)",
            file=sys.stderr,
            flush=True,
        )
        if slurm is not None:  # here, once, into the cache the jobs load them from, rather than in every job
            compile_apart()
    return slurm, params, url


def _paths_and_passes(
    engine, url: str, n: int, params: Params, dask, progress: bool, max_attempts: int, workerless, glued: bool
) -> RunResult:
    """The run's paths (:func:`packings.service.coordinator.run_enumeration`) and, with ``glued``, a glued
    pass after each complete run of them, the paths again over what a pass added, until a pass adds none."""
    from packings.service.coordinator import run_enumeration

    def paths() -> RunResult:
        bar = _progress_bar(progress)
        try:
            return run_enumeration(
                engine,
                url,
                n,
                params,
                dask.client,
                on_progress=bar if progress else None,
                max_attempts=max_attempts,
                workerless_timeout=workerless,
                revive=dask.revive_workers,
            )
        finally:
            bar.close()

    result = paths()
    passes = []
    while glued and result.status == "complete":
        report = _glued_pass(
            engine,
            url,
            n,
            params,
            result.run_id,
            dask.client,
            progress,
            before=dask.fresh_workers,
            max_attempts=max_attempts,
            workerless_timeout=workerless,
            revive=dask.revive_workers,
        )
        if report is None:
            break
        passes.append(report)
        if not report.expansions_added:
            break
        result = paths()
    result.catalysis = passes
    return result


def _refuse_sqlite_for_slurm(url: str) -> None:
    """Slurm's jobs run on other machines: they need a database server (:class:`UsageError` otherwise).
    A SQLite file on a shared file system is no answer: SQLite's locks are not to be trusted over NFS
    or Lustre, and many writers at once would corrupt it or stall."""
    from packings.service.db import parse_url

    if parse_url(url).get_backend_name() == "sqlite":
        raise UsageError(
            "--slurm needs a PostgreSQL database that the batch jobs reach (--db postgresql://user@host/db): "
            "SQLite files cannot be shared safely between machines"
        )


def _glued_pass(
    engine,
    url: str,
    n: int,
    params,
    run_id: int,
    client,
    progress: bool,
    before=None,
    max_attempts: int = 3,
    workerless_timeout: float | None = None,
    revive=None,
):
    """A glued catalysis pass into ``run_id`` over the clusters of n stored since the passes before it
    (:func:`packings.service.catalysis.covered`), on ``client``'s workers; its report, or None if there are none.
    ``before()`` is called first when there is a pass to make (``packings enumerate`` gives its local
    workers fresh processes there, so that a pass's record of the remainders seen is not added on top of
    what the paths left in them).  ``max_attempts``, ``workerless_timeout`` and ``revive`` are the run's
    (:func:`packings.service.catalysis.catalyse`)."""
    from packings.service.catalysis import catalyse, count_stored, covered
    from packings.service.db import sessions
    from packings.service.plugin import DatabasePlugin

    Session_ = sessions(engine)
    after = covered(Session_, run_id)
    if not count_stored(Session_, n, after):
        return None
    if before is not None:
        before()
    bar, shown = pass_bar(f"clusters of {n} (glued)", "cluster", not progress, off_terminal=True)
    try:
        return catalyse(
            Session_,
            n,
            params,
            glued=True,
            client=client,
            plugin=DatabasePlugin(url),
            after=after,
            on_progress=shown,
            max_attempts=max_attempts,
            workerless_timeout=workerless_timeout,
            revive=revive,
        )
    finally:
        bar.close()


def pass_bar(desc: str, unit: str, quiet: bool, off_terminal: bool = False):
    """A progress bar on standard error (none when ``quiet``; off a terminal tqdm's own choice, none, unless
    ``off_terminal``, as the expansions' bar of a run) and the ``on_progress(done, total)`` that moves it,
    for a catalysis pass.  The bar is drawn from the first progress on (as the expansions' bar: not while
    a cluster starts, whose lines would run into it); the first value has only ``close()``."""
    from tqdm import tqdm

    disable = True if quiet else False if off_terminal else None
    bars: list = []

    def progress(done: int, total: int) -> None:
        if not bars:
            bars.append(tqdm(total=0, unit=unit, desc=desc, file=sys.stderr, disable=disable))
        bar = bars[0]
        bar.total = total
        bar.n = done
        bar.refresh()

    class Bar:
        def close(self) -> None:
            if bars:
                bars[0].close()

    return Bar(), progress
