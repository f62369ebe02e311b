"""The ``packings`` command line.

Every command takes ``--db URL`` (default: the ``PACKINGS_DB`` environment
variable, else ``sqlite:///packings.db``).  Errors a user can cause end in one
line on standard error (``packings: error: ...``) and a non-zero exit status.
"""

from __future__ import annotations

import gc
import json
import logging
import os
import signal
import sys
import threading
from dataclasses import asdict

import click

from packings.service import export as _export
from packings.service.api import connect, resolve_url, selection_query
from packings.service.dask_cluster import DASHBOARD_ADDRESS
from packings.service.errors import Interrupted, PackingsError, SigTerm, Terminated, UsageError
from packings.service.options import db_option, width_option
from packings.service.paper import against_paper, verdict
from packings.service.plot_commands import plot
from packings.service.run import pass_bar, timeouts
from packings.service.validate import check_cluster_choice, check_dashboard_address, check_n, int_range
from packings.workers.params import Params

# What this module imports when it is loaded is kept light (no SQLAlchemy, numpy or Dask): `packings
# enumerate` starts the fork server of its local cluster's workers first thing (start_fork_server), and
# every 0.1 s before it is 0.1 s more before the workers can start.  The commands import what they use.

#: where the work runs: a local cluster of K workers, or an existing Dask cluster
workers_option = click.option(
    "--workers",
    "n_workers",
    type=int_range("workers"),
    default=None,
    help="Worker processes of the local Dask cluster (default: one per core).",
)
scheduler_option = click.option(
    "--scheduler",
    default=None,
    metavar="ADDRESS",
    help="Join an existing Dask cluster, e.g. tcp://host:8786, instead of starting one.",
)
dashboard_option = click.option(
    "--dashboard-address",
    default=DASHBOARD_ADDRESS,
    show_default=True,
    metavar="HOST:PORT",
    help="Where a local cluster serves the Dask dashboard and its packings page (another port if taken).",
)


def open_db(db_url: str | None, create: bool = False, migrate: bool = False):
    from packings.service.db import open_database

    return open_database(resolve_url(db_url), create=create, migrate=migrate)


def format_counts(n: int, by_contacts: dict[int, int]) -> str:
    """The paper's table: clusters by number of contacts, relative to 3n - 6."""
    lines = [
        f"n = {n}: {_export.counted(sum(by_contacts.values()), 'rigid cluster')}",
        f"{'contacts':>10} {'3n-6+':>6} {'clusters':>9}",
    ]
    for m, count in sorted(by_contacts.items()):
        lines.append(f"{m:>10} {m - (3 * n - 6):>+6} {count:>9}")
    return "\n".join(lines)


LOG_ENV = "PACKINGS_LOG"  #: the log level when no -v is given (default WARNING)


def configure_logging(verbose: int) -> None:
    """What an operator needs to see on standard error: the ``packings`` loggers' warnings (faults
    recovered: workers lost, leases put back, expansions retried), with ``-v`` also what a run does,
    ``-vv`` everything (the level also comes from ``$PACKINGS_LOG``)."""

    class BarHandler(logging.StreamHandler):
        """Each record on a line of its own above the progress bars being drawn (tqdm.write), not
        over them."""

        def emit(self, record: logging.LogRecord) -> None:
            if "tqdm" not in sys.modules:  # no bar can be drawn
                return super().emit(record)
            from tqdm import tqdm

            try:
                tqdm.write(self.format(record), file=self.stream)
            except Exception:  # noqa: BLE001 - as logging's own handlers: reported, never raised
                self.handleError(record)

    default = os.environ.get(LOG_ENV, "WARNING").upper()
    level = {0: getattr(logging, default, logging.WARNING), 1: logging.INFO}.get(verbose, logging.DEBUG)
    handler = BarHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s packings %(levelname)s: %(message)s", "%H:%M:%S"))
    logger = logging.getLogger("packings")
    logger.handlers[:] = [handler]
    logger.setLevel(level)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="packings", prog_name="packings")
@click.option("-v", "--verbose", count=True, help="Log what a run does (-v), or everything (-vv), on standard error.")
def cli(verbose: int) -> None:
    """Enumerate every rigid cluster of n identical hard spheres."""
    configure_logging(verbose)


@cli.command("enumerate")
@click.argument("n", type=int)
@db_option
@workers_option
@scheduler_option
@click.option(
    "--slurm",
    is_flag=True,
    help="Run the workers as Slurm batch jobs (needs packings[slurm] and a PostgreSQL --db the jobs reach).",
)
@click.option("--jobs", type=int_range("jobs"), default=None, help="With --slurm: jobs kept running (default 1).")
@click.option(
    "--cores",
    type=int_range("cores"),
    default=None,
    help="With --slurm: cores per job, one single-threaded worker process each (default 1).",
)
@click.option("--memory", default=None, metavar="SIZE", help="With --slurm: memory per job (default 2GiB a core).")
@click.option("--queue", default=None, metavar="PARTITION", help="With --slurm: the partition (default Slurm's).")
@click.option(
    "--walltime",
    default=None,
    metavar="TIME",
    help="With --slurm: each job's time limit, e.g. 04:00:00 (default dask-jobqueue's configuration, 30 min); "
    "a job that reaches it is replaced.",
)
@click.option(
    "--max-break",
    type=int_range("max_break"),
    default=None,
    help="Largest number of contacts broken at once (default: no cap, every size up to m - rank + 1 as the "
    "paper for n <= 14; a cap is for restricted runs of large n).",
)
@click.option(
    "--min-contacts",
    type=int,
    default=None,
    help="Keep only clusters with at least this many contacts (a restricted run, e.g. of the ground states "
    "of large N); above 3N - 6 the run starts from a close-packed fragment with that many (a beam search's, "
    "else the best of every close-packed fragment listed: minutes from N = 14).",
)
@click.option(
    "--max-attempts",
    type=int_range("max_attempts"),
    default=3,
    show_default=True,
    help="Tries per expansion before it is marked failed.",
)
@dashboard_option
@click.option(
    "--glued/--no-glued",
    default=True,
    show_default=True,
    help="After the paths, move one sphere of every cluster onto each contact triangle (as `catalyse N --glued`), "
    "add the rigid clusters no path reached and expand them, until nothing new is found (n = 11 and 13 have "
    "one such cluster); --no-glued follows the paths alone.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the counts and diagnostics as JSON.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def enumerate_cmd(
    n: int,
    db_url: str | None,
    n_workers: int | None,
    scheduler: str | None,
    slurm: bool,
    jobs: int | None,
    cores: int | None,
    memory: str | None,
    queue: str | None,
    walltime: str | None,
    max_break: int | None,
    min_contacts: int | None,
    max_attempts: int,
    dashboard_address: str,
    glued: bool,
    as_json: bool,
    quiet: bool,
) -> None:
    """Enumerate the rigid clusters of N spheres into the database and print them by number of contacts.

    Resumes the run with the same N and parameters if the database has one
    (an interrupted run goes on where it stopped; a complete one just prints).
    Glued catalysis passes follow the paths unless --no-glued is given (a pass
    that ran to its end is not made again; one over the clusters stored since is).
    With --slurm the workers run as Slurm batch jobs (docs/cli.md).
    """
    from packings.service import run

    check_dashboard_address(dashboard_address, option=True)
    given = {"jobs": jobs, "cores": cores, "memory": memory, "queue": queue, "walltime": walltime}
    given = {k: v for k, v in given.items() if v is not None}
    if given and not slurm:
        raise click.UsageError(f"--{', --'.join(given)} only with --slurm")
    check_cluster_choice(n_workers, scheduler, slurm=slurm, options=True)
    try:
        result = run.enumerate(
            n,
            db_url,
            workers=n_workers,
            scheduler=scheduler,
            slurm=given if slurm else None,
            max_break=max_break,
            min_contacts=min_contacts,
            max_attempts=max_attempts,
            progress=not quiet,
            dashboard_address=dashboard_address,
            glued=glued,
        )
    except KeyboardInterrupt as e:  # the run put its leases back: one line (click would print a newline first)
        raise _stopped(e) from None
    _print_run(n, result, resolve_url(db_url), min_contacts, as_json)
    for err in result.errors[:10]:
        click.echo(f"packings: failed task: {err}", err=True)
    if result.status != "complete":
        raise click.ClickException(
            f"run {result.run_id} is {result.status}: {len(result.errors)} expansion(s) "
            "failed (see `packings status`); rerun the same command to retry them"
        )


def _print_run(n: int, result, url: str, min_contacts: int | None, as_json: bool) -> None:
    """``enumerate``'s output: its counts against the paper's, diagnostics, time and glued passes, as a table
    or (``as_json``) one JSON object."""
    from packings.service.db import display_url, parse_url

    against = against_paper(n, result.by_contacts, min_contacts)
    gc.freeze()  # what is left is freed by the exit: skip the collector's last pass over it (0.2-0.3 s)
    if as_json:
        click.echo(
            json.dumps(
                {
                    "n": n,
                    "run": result.run_id,
                    "status": result.status,
                    "total": result.total,
                    "by_contacts": {str(k): v for k, v in result.by_contacts.items()},
                    "diagnostics": result.diagnostics,
                    "seconds": round(result.seconds, 2),
                    "total_seconds": round(result.total_seconds, 2),
                    "paper": against,
                    "catalysis": [r.to_dict() for r in result.catalysis],  # the glued passes made (none: [])
                }
            )
        )
    else:
        from packings.service.catalysis import format_report

        click.echo(format_counts(n, result.by_contacts))
        said = verdict(n, against, result.status == "complete", min_contacts)
        if said is not None:
            click.echo(said)
        click.echo("diagnostics: " + ", ".join(f"{k} {v}" for k, v in result.diagnostics.items()))
        took = (
            f"in {result.total_seconds:.1f} s, {result.seconds:.1f} s of it now (resumed)"
            if result.resumed
            else f"in {result.seconds:.1f} s"
        )
        click.echo(f"run {result.run_id}: {result.status} {took}; database {display_url(parse_url(url))}")
        for report in result.catalysis:  # what each pass added, the paths after it expanded
            click.echo(format_report(report, expanded=result.status == "complete"))


@cli.command("catalyse")
@click.argument("n", type=int)
@db_option
@click.option(
    "--spheres",
    "k",
    type=int_range("spheres"),
    default=1,
    show_default=True,
    help="Spheres deleted from each stored cluster of N + K spheres.",
)
@click.option(
    "--max-break",
    type=int_range("max_break"),
    default=None,
    help="As for enumerate (default: no cap): chooses the run of N that the clusters found are added to.",
)
@click.option(
    "--min-contacts",
    type=int,
    default=None,
    help="As for enumerate: keep only remainders with at least this many contacts (and choose that run).",
)
@click.option(
    "--glued",
    is_flag=True,
    help="Instead, move one sphere of every stored cluster of N onto each contact triangle (the "
    "parents of N + 1 are made by gluing, not read: no run of N + 1 is needed).",
)
@click.option(
    "--close-packed",
    "close_packed",
    type=int_range("close_packed"),
    default=None,
    metavar="M",
    help="No parents: every close-packed fragment of N spheres with at least M contacts (fcc, hcp and "
    "every other stacking), decided in this process; the rigid ones not yet stored are added "
    "(found_by = close-packed).",
)
@workers_option
@scheduler_option
@dashboard_option
@click.option(
    "--max-attempts",
    type=int_range("max_attempts"),
    default=3,
    show_default=True,
    help="Tries per batch of parents whose task fails before the pass stops.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def catalyse_cmd(
    n: int,
    db_url: str | None,
    k: int,
    max_break: int | None,
    min_contacts: int | None,
    glued: bool,
    close_packed: int | None,
    n_workers: int | None,
    scheduler: str | None,
    dashboard_address: str,
    max_attempts: int,
    as_json: bool,
    quiet: bool,
) -> None:
    """Delete K spheres from every stored cluster of N + K spheres and add the rigid remainders that are not
    yet stored to the run of N (found_by = catalysis), with an expansion each: `packings enumerate N`
    afterwards follows the paths from them.  Finds clusters no path from the seed reaches (at N = 11 one).
    With --glued, the clusters of N + 1 are those made by gluing a sphere onto a stored cluster of N.
    The parents are shared out among the workers of a local Dask cluster, or of an existing one.
    With --close-packed M, there are no parents: the close-packed fragments of N spheres with at least
    M contacts are listed and decided (finds, at N = 11, the cluster no path reaches)."""
    check_n(n)
    check_dashboard_address(dashboard_address, option=True)
    if close_packed is not None:
        if glued or k != 1 or n_workers is not None or scheduler is not None:
            raise click.UsageError(
                "--close-packed lists fragments in this process: not with --glued, --spheres, --workers or --scheduler"
            )
        _close_packed(n, close_packed, db_url, Params(max_break=max_break, min_contacts=min_contacts), as_json, quiet)
        return
    if glued and k != 1:
        raise click.UsageError("--glued moves one sphere: --spheres must be 1")
    check_n(n + k)
    check_cluster_choice(n_workers, scheduler, options=True)
    params = Params(max_break=max_break, min_contacts=min_contacts)
    timeouts(local=scheduler is None)  # a bad value in the environment said before anything starts
    from packings.service.dask_cluster import start_fork_server

    if scheduler is None:
        start_fork_server()  # the local cluster's workers load what they need while the database is opened
    from packings.service.catalysis import NoParents, parents_stored
    from packings.service.db import sessions

    url = resolve_url(db_url)
    engine = open_db(db_url)
    try:
        parents_stored(sessions(engine, readonly=True), n if glued else n + k)  # said before Dask starts
    except NoParents as e:
        engine.dispose()
        raise click.ClickException(str(e) + _glued_instead(n, k, glued)) from None
    # shown off a terminal too (a log file), as enumerate's bars are: a pass may take many minutes
    bar, progress = pass_bar(f"clusters of {n if glued else n + k}", "cluster", quiet, off_terminal=True)

    work = dict(spheres=k, on_progress=progress, glued=glued, max_attempts=max_attempts)
    try:
        report = _pass_on_dask(engine, url, n, params, scheduler, n_workers, quiet or as_json, dashboard_address, work)
    except KeyboardInterrupt as e:  # what was stored stays (the pass is idempotent): one line
        raise _stopped(e) from None
    except NoParents as e:
        raise click.ClickException(str(e)) from None
    finally:
        bar.close()
        engine.dispose()
    _echo_report(report, n, as_json)


def _pass_on_dask(
    engine, url: str, n: int, params: Params, scheduler, n_workers, quiet: bool, dashboard_address: str, work: dict
):
    """The catalysis pass of ``catalyse N`` (:func:`packings.service.catalysis.catalyse` with ``work``) on a new
    local Dask cluster or an existing one, wired as ``enumerate`` wires its run: a local cluster's lost
    workers replaced, and stopped after its time without any; an existing scheduler reached again for
    :func:`packings.service.run.timeouts`' window when it is lost."""
    from packings.service.catalysis import catalyse
    from packings.service.dask_cluster import dask_client
    from packings.service.db import sessions
    from packings.service.plugin import DatabasePlugin

    workerless, reconnect = timeouts(local=scheduler is None)
    plugin = DatabasePlugin(url)
    with dask_client(
        scheduler,
        n_workers,
        quiet,
        plugins=(plugin,),
        database=url,
        dashboard_address=dashboard_address,
        reconnect_seconds=reconnect,
    ) as dask:
        client = dask.client
        if scheduler:  # an existing cluster's workers get the engine now (a local one's as they started)
            client.register_plugin(plugin)
        return catalyse(
            sessions(engine),
            n,
            params,
            client=client,
            plugin=plugin,
            workerless_timeout=workerless,
            revive=dask.revive_workers,
            **work,
        )


def _glued_instead(n: int, k: int, glued: bool) -> str:
    """What to say beside "run `packings enumerate N + 1` first" when catalyse N has no parents: what that
    costs (the count grows like (n-5)!: n + 1 has about n - 4 times the clusters of n), and the pass
    that needs no clusters of N + 1 (--glued makes its parents from those of N)."""
    if glued or k != 1:
        return ""
    return (
        f" (n = {n + 1} has about {max(n - 4, 1)} times the clusters of n = {n}, each dearer to expand), or "
        f"`packings catalyse {n} --glued`, which makes its parents from the stored clusters of {n}"
    )


def _echo_report(report, n: int, as_json: bool) -> None:
    """A catalysis report as JSON, or as text with what to run next."""
    from packings.service.catalysis import format_report

    if as_json:
        click.echo(json.dumps(report.to_dict()))
        return
    click.echo(format_report(report))
    if report.new:
        click.echo(f"run `packings enumerate {n}` to expand them")


def _close_packed(n: int, m: int, db_url: str | None, params: Params, as_json: bool, quiet: bool) -> None:
    """``packings catalyse N --close-packed M``: the close-packed fragments, decided and stored."""
    from packings.service.catalysis import close_packed_pass
    from packings.service.db import sessions

    engine = open_db(db_url)
    bar, progress = pass_bar(f"fragments of {n}", "fragment", quiet or as_json)

    try:
        report = close_packed_pass(sessions(engine), n, params, m, on_progress=progress)
    except KeyboardInterrupt as e:  # what was stored stays (the pass is idempotent): one line
        raise _stopped(e) from None
    except ValueError as e:  # no run of (N, parameters) yet, and nothing to seed one with: nothing written
        raise click.ClickException(str(e)) from None
    finally:
        bar.close()
        engine.dispose()
    _echo_report(report, n, as_json)


@cli.group("db")
def db_group() -> None:
    """The database schema (Alembic migrations)."""


@db_group.command("upgrade")
@db_option
def db_upgrade(db_url: str | None) -> None:
    """Create the schema, or migrate it to this code's version."""
    from packings.service.db import current_revision, display_url, head_revision

    engine = open_db(db_url, create=True, migrate=True)
    click.echo(f"{display_url(engine.url)}: schema {current_revision(engine)} (this code: {head_revision()})")
    _backfill(engine, recompute=False)
    engine.dispose()


@db_group.command("backfill")
@db_option
@click.option("--all", "recompute", is_flag=True, help="Recompute every cluster's facts, not only missing ones.")
def db_backfill(db_url: str | None, recompute: bool) -> None:
    """Compute the facts (lattice, min_gap) of clusters stored by an older version.

    `packings db upgrade` runs this itself; it is safe to interrupt and rerun."""
    engine = open_db(db_url)
    _backfill(engine, recompute)
    engine.dispose()


def _backfill(engine, recompute: bool) -> None:
    from tqdm import tqdm

    from packings.service import store
    from packings.service.db import sessions

    Session_ = sessions(engine)
    with Session_() as s:
        todo = store.to_backfill(s, recompute)
    if not todo:
        return
    with tqdm(total=todo, desc="facts", unit="cluster", disable=None) as bar:
        done = store.backfill(Session_, recompute, on_batch=lambda k: bar.update(k - bar.n))
    click.echo(f"computed the facts of {done} cluster{'s' if done != 1 else ''}")


@db_group.command("version")
@db_option
def db_version(db_url: str | None) -> None:
    """Print the database's schema version and this code's."""
    from packings.service.db import connect_error, current_revision, head_revision, make_engine

    engine = make_engine(resolve_url(db_url))
    try:
        rev = current_revision(engine)
    except Exception as e:
        raise connect_error(engine, e) from None
    finally:
        engine.dispose()
    head = head_revision()
    state = "up to date" if rev == head else ("empty" if rev is None else "needs `packings db upgrade`")
    click.echo(f"database: {rev or 'none'}\ncode:     {head}\n{state}")


@cli.command("status")
@db_option
@click.option("--json", "as_json", is_flag=True, help="As JSON.")
def status_cmd(db_url: str | None, as_json: bool) -> None:
    """Runs and their frontier (expansions pending, leased, done, failed), and the faults recovered:
    expansions put back after a worker or coordinator was lost (retries, not counted as attempts), and
    tasks of one expansion lost again (isolated, each an attempt)."""
    with _catalogue(db_url) as cat:
        rows = cat.runs()
    if as_json:
        click.echo(json.dumps(rows))
        return
    if not rows:
        click.echo("no runs yet: `packings enumerate N` starts one")
        return
    cols = [
        "run",
        "n",
        "status",
        "clusters",
        "pending",
        "leased",
        "done",
        "failed",
        "retries",
        "isolated_failures",
        "max_break",
        "seconds",
        "started",
    ]
    header = [{"isolated_failures": "isolated"}.get(c, c) for c in cols]
    click.echo(_export.table(header, [[r[c] for c in cols] for r in rows]))


@cli.command("stats")
@db_option
@click.option("--n", "n", type=int, default=None, help="Only this n.")
@click.option("--json", "as_json", is_flag=True, help="A JSON list with one object per n.")
@click.option(
    "--kappa",
    type=click.FloatRange(min=0.0, min_open=True),
    default=None,
    help="Add each cluster's and each number of contacts' equilibrium probability at this sticky parameter κ.",
)
@width_option
def stats_cmd(db_url: str | None, n: int | None, as_json: bool, kappa: float | None, width: float | None) -> None:
    """What the catalogue contains, per n, in the paper's style.

    Clusters, singular clusters and close-packed fragments by number of
    contacts; fragments by lattice; adjacency matrices with several
    geometries; the smallest gaps; paths and circular paths; the fit of the
    totals to b·(n−5)!.  With --kappa, the equilibrium probabilities from the
    stored partition functions (an n where they are not defined says why;
    with --n, that is an error)."""
    from packings.service.probabilities import UndefinedProbabilities, format_probabilities
    from packings.service.stats import format_fit, format_stats

    if width is not None and kappa is None:
        raise click.UsageError("--width is the square well of --kappa's probabilities: give --kappa too")
    with _catalogue(db_url) as cat:
        rows, fit = cat.stats(n), cat.fit()
        if n is not None and not rows:  # as plot and audit: an n asked for that the database does not hold
            raise click.ClickException(f"no clusters with n = {n} in the database")
        for r in rows if kappa is not None else ():
            try:
                r["probabilities"] = cat.probabilities(r["n"], kappa, width)
            except UndefinedProbabilities as e:
                if n is not None:
                    raise click.ClickException(str(e)) from None
                r["probabilities"] = {"undefined": str(e)}
    if as_json:
        click.echo(json.dumps(rows))
        return
    if not rows:
        click.echo("no clusters" + (f" with n = {n}" if n is not None else ""))
        return
    blocks = [format_stats(r) for r in rows]
    if kappa is not None:
        blocks = [
            b + "\n" + (p.get("undefined") or format_probabilities(p))
            for b, p in zip(blocks, (r["probabilities"] for r in rows))
        ]
    click.echo("\n\n".join(blocks) + "\n\n" + format_fit(fit))


@cli.command("audit")
@db_option
@click.option("--n", "n", type=int, default=None, help="Only this n.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object: the three lists and the tolerances.")
def audit_cmd(db_url: str | None, n: int | None, as_json: bool) -> None:
    """Look for junk clusters: (a) clusters with a non-contact pair within tol_a0 of touching, and what
    adding the pair gives (a stored cluster: a near copy of it); (b) pre-stress margins within a factor
    of 10 of tol_psd; (c) two geometries of one contact graph within 100 tol_d.  A clean catalogue has
    (a) and (c) empty.  Exits 0 whatever it finds (it is a report); 1 if --n names an n the database does not hold."""
    from packings.service.audit import audit, format_audit
    from packings.service.db import sessions

    engine = open_db(db_url)
    try:
        with sessions(engine, readonly=True)() as s:
            report = audit(s, n)
    finally:
        engine.dispose()
    if n is not None and not report.tolerances:  # as stats and plot: an n the database does not hold
        raise click.ClickException(f"no clusters with n = {n} in the database")
    click.echo(json.dumps(report.to_dict()) if as_json else format_audit(report))


# --------------------------------------------------------------------------- queries: select, show, export


_SELECTION_HELP = (
    "SELECTION is comma-separated terms, all of which must hold: key (a boolean key is true), "
    "!key or 'not key' (false), key OP value with OP one of = != < <= > >=; e.g. "
    "'n=10,contacts<24,singular', '!singular,min_gap>0.1', hyperstatic, run=1.  Keys:\n\n\b\n"
)


class _SelectionCommand(click.Command):
    """A command taking a SELECTION, whose help ends with the selection's keys (built when the help is
    shown: they come from packings.service.selection, which loads SQLAlchemy)."""

    def format_epilog(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        from packings.service.selection import describe_keys

        self.epilog = _SELECTION_HELP + describe_keys()
        super().format_epilog(ctx, formatter)


_TABLE_COLUMNS = [
    "id",
    "n",
    "contacts",
    "embedding",
    "singular",
    "flexes",
    "stresses",
    "min_gap",
    "lattice",
    "certificate",
]


def _check_selection(selection: str | None, **kw) -> None:
    """A bad selection or sort key is reported before the database is opened."""
    selection_query(selection, **kw)


def _catalogue(db_url: str | None):
    """The catalogue at ``--db`` (:func:`packings.service.api.connect`), to use in a ``with``."""
    return connect(db_url)


def _echo_chunks(chunks) -> None:
    for chunk in chunks:
        click.echo(chunk, nl=False)


TABLE_LIMIT = 20  #: rows a table shows unless --limit says otherwise (as ase db)


def _cell(name: str, v):
    if isinstance(v, float):
        return f"{v:.6g}"
    if name == "certificate" and len(v) > 16:
        return v[:13] + "..."
    return v


def _table_row(f: dict, columns: list[str]) -> list:
    return [_cell(c, f[c]) for c in columns]


def _columns(spec: str | None) -> list[str]:
    """The columns of ``-c``: a comma list of facts, or ``+fact,...`` to add to the default ones (the first
    ``+`` adds every one of the list: ``+found_by,source_id`` as ``+found_by,+source_id``)."""
    if not spec:
        return list(_TABLE_COLUMNS)
    names = [s.strip() for s in spec.split(",") if s.strip()]
    adding = bool(names) and names[0].startswith("+")
    if not adding and any(s.startswith("+") for s in names):
        raise click.UsageError(
            "give either columns (-c id,n,lattice) or columns to add, the list starting with + (-c +margin,found_by)"
        )
    names = [s.lstrip("+") for s in names]
    unknown = [s for s in names if s not in _export.FACTS]
    if unknown:
        raise click.UsageError(f"unknown column {unknown[0]!r}; the columns are {', '.join(_export.FACTS)}")
    return list(_TABLE_COLUMNS) + [s for s in names if s not in _TABLE_COLUMNS] if adding else names


@cli.command("select", cls=_SelectionCommand)
@click.argument("selection", required=False, default="")
@db_option
@click.option("--json", "as_json", is_flag=True, help="A JSON list: every fact, coords and contact_list.")
@click.option("--csv", "as_csv", is_flag=True, help="CSV with a header line (no coordinates).")
@click.option("--count", "as_count", is_flag=True, help="Only the number of clusters selected.")
@click.option(
    "-L",
    "--limit",
    type=click.IntRange(min=0),
    default=None,
    help=f"At most this many clusters; 0: all (default: {TABLE_LIMIT} in a table, all in JSON or CSV).",
)
@click.option(
    "-c",
    "--columns",
    default=None,
    metavar="COLS",
    help="The table's or CSV's columns, comma-separated (e.g. id,n,lattice,margin), or +COL,COL,... to add "
    "to the default ones.",
)
@click.option("--sort", default=None, metavar="KEY", help="Sort by KEY (-KEY: descending); default n, contacts, id.")
def select_cmd(
    selection: str,
    db_url: str | None,
    as_json: bool,
    as_csv: bool,
    as_count: bool,
    limit: int | None,
    columns: str | None,
    sort: str | None,
) -> None:
    """The stored clusters that match SELECTION (default: all), as a table, JSON or CSV."""
    if as_json + as_csv + as_count > 1:
        raise click.UsageError("give at most one of --json, --csv, --count")
    cols = _columns(columns)
    table_view = not (as_json or as_csv or as_count)
    if limit is None and table_view:
        limit = TABLE_LIMIT
    limit = None if limit == 0 else limit
    _check_selection(selection, sort=sort)
    with _catalogue(db_url) as cat:
        if as_count:
            click.echo(cat.count(selection))
            return
        rows = cat.select(selection, sort=sort, limit=limit)
        if as_json:
            _echo_chunks(_export.to_json(r.record() for r in rows))
        elif as_csv:
            _echo_chunks(_export.to_csv((r.facts for r in rows), columns=cols if columns else _export.FACTS))
        else:
            table = [_table_row(r.facts, cols) for r in rows]
            if not table:
                click.echo("no clusters match")
                return
            total = cat.count(selection) if limit is not None and len(table) == limit else len(table)
            footer = (
                _export.counted(total, "cluster")
                if total == len(table)
                else f"{len(table)} of {total} clusters ({total - len(table)} more: --limit 0 shows all)"
            )
            click.echo(_export.table(cols, table) + "\n" + footer)


@cli.command("show")
@click.argument("cluster_id", metavar="ID", type=int)
@db_option
@click.option("--json", "as_json", is_flag=True, help="One JSON object.")
def show_cmd(cluster_id: int, db_url: str | None, as_json: bool) -> None:
    """Cluster ID in full: every fact, the exact coordinates, the contacts, the
    paths leaving and reaching it, and the runs whose frontier holds it."""
    with _catalogue(db_url) as cat:
        row = cat.get(cluster_id)
        rec, info = row.record(), cat.links(cluster_id)
        exact = _exact(row)
    if as_json:
        click.echo(json.dumps({**rec, **info, "exact": exact}))
        return
    out = [f"cluster {rec['id']}: n = {rec['n']}, {rec['contacts']} contacts (3n-6{rec['excess']:+d}, {rec['static']})"]
    out += [
        f"  {k:<13} {'' if rec[k] is None else repr(rec[k]) if isinstance(rec[k], float) else rec[k]}"
        for k in _export.FACTS
    ]
    if exact is None:
        out.append("  exact root    - (a flex: rigid by the pre-stress test, which this proof does not cover)")
    elif exact["status"] in ("proved", "gap"):
        out.append(
            f"  exact root    {exact['status']}: within {exact['radius']:.2g} of these coordinates "
            f"(Kantorovich, h = {exact['h']:.2g})"
            + ("" if exact["gap"] is None else f", smallest gap there >= {exact['gap']:.3g}")
            + (f", other contacts' |f| <= {exact['others']:.2g}" if exact["others"] else "")
        )
    else:
        out.append(
            f"  exact root    not proved ({exact['status']}" + (f", h = {exact['h']:.2g}" if exact["h"] else "") + ")"
        )
    out += [
        "coordinates (unit: sphere diameter):",
        _export.table(["i", "x", "y", "z"], [[i, *map(repr, x)] for i, x in enumerate(rec["coords"])]),
    ]
    pairs = [f"{i}-{j}" for i, j in rec["contact_list"]]
    out += [f"contacts ({len(pairs)}):"] + ["  " + " ".join(pairs[k : k + 12]) for k in range(0, len(pairs), 12)]
    by = ", ".join(f"{o} {c}" for o, c in info["leaving_by_outcome"].items())
    out += [
        f"paths leaving: {info['paths_leaving']}" + (f" ({by})" if by else ""),
        f"paths reaching: {info['paths_reaching']} from {_export.counted(info['reached_from'], 'cluster')}",
    ]
    out += [
        f"run {r['run']} (n = {r['n']}, {r['run_status']}): expansion {r['expansion']}"
        + ("" if r["paths"] is None else f", {r['paths']} paths followed")
        for r in info["runs"]
    ] or ["in no run's frontier"]
    click.echo("\n".join(out))


def _exact(row) -> dict | None:
    """:meth:`packings.service.api.Row.exact` as a dict (None for a cluster with a flex)."""
    e = row.exact()
    return None if e is None else asdict(e)


@cli.command("export", cls=_SelectionCommand)
@click.argument("selection", required=False, default="")
@click.argument("network_n", metavar="[N]", required=False, type=int)
@click.option("--n", "n", type=int, default=None, help="Only clusters of N spheres.")
@click.option(
    "--format",
    "fmt",
    type=click.Choice(_export.FORMATS),
    default=None,
    help="Default: from the suffix of -o (.extxyz, .xyz, .json), else extxyz.",
)
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write to this file (replaced whole, never half-written); default standard output.",
)
@db_option
def export_cmd(
    selection: str, network_n: int | None, n: int | None, fmt: str | None, output: str | None, db_url: str | None
) -> None:
    """Write the clusters that match SELECTION (default: all), ordered by n, contacts, id: extended XYZ
    (readable by ase.io.read), plain XYZ, or JSON with every fact, coordinates and contacts.

    `packings export network N -o FILE` writes instead the network of the clusters of N and the paths
    between them, as GraphML (.graphml) or networkx's node-link JSON (.json, the default on standard
    output): nodes with their facts, edges with the paths' multiplicity, fewest steps and broken
    contacts, self-loops for the paths that came back to their start (circles and rearrangements)."""
    if selection == "network":
        _export_network(network_n, output, db_url)
        return
    if network_n is not None:
        raise click.UsageError(
            f"one SELECTION only (got {selection!r} and {network_n}); `export network N` for the network"
        )
    fmt = fmt or _export.format_for(output)
    _check_selection(selection)
    written = 0
    with _catalogue(db_url) as cat:
        rows = cat.select(selection, **({} if n is None else {"n": n}))

        def records():
            nonlocal written
            for r in rows:
                written += 1
                yield r.record()

        if not _write_chunks(_export.render(fmt, records()), output):
            return
    click.echo(f"wrote {_export.counted(written, 'cluster')} ({fmt}) to {output}")


def _write_chunks(chunks, output: str | None) -> bool:
    """Write the text ``chunks`` to the file ``output`` (replaced whole; True) or to standard output (None;
    False, and nothing more is said)."""
    if output is None:
        _echo_chunks(chunks)
        return False
    try:
        _export.write_atomic(output, chunks)
    except OSError as e:
        raise click.ClickException(f"cannot write {output}: {e.strerror or e}") from None
    return True


def _export_network(n: int | None, output: str | None, db_url: str | None) -> None:
    from packings.service import network

    if n is None:
        raise click.UsageError("`packings export network N`: give N")
    fmt = network.format_for(output)
    with _catalogue(db_url) as cat:
        g = cat.network(n)
    if not _write_chunks([network.text(g, fmt)], output):
        return
    d = network.summary(g)
    click.echo(
        f"wrote the network of n = {n} ({fmt}) to {output}: {_export.counted(d['clusters'], 'cluster')}, "
        f"{_export.counted(d['edges'], 'edge')} between two clusters and {d['self_loops']} self-loops, "
        f"{_export.counted(d['paths'], 'path')} ({d['circular']} circular, {d['rearranged']} rearranged), "
        f"{_export.counted(d['components'], 'component')}"
    )


cli.add_command(plot)  # packings.service.plot_commands; matplotlib is imported only when it draws


def _database_error(e: Exception) -> str | None:
    """The one line for a database's error (packings.service.db.DatabaseError: one a user can fix; SQLAlchemy's:
    e.g. the server went away mid-command, and transactions rolled back), None for any other error."""
    from sqlalchemy.exc import SQLAlchemyError

    from packings.service.db import DatabaseError, first_line

    if isinstance(e, DatabaseError):
        return str(e)
    if isinstance(e, SQLAlchemyError):
        return f"database: {first_line(e)}"
    return None


def _stopped(e: BaseException | None) -> Interrupted:
    """What stopped a command: SIGTERM (our handler's SigTerm) or Ctrl-C."""
    return Terminated() if isinstance(e, SigTerm) else Interrupted()


def _on_sigterm(signum, frame) -> None:
    raise SigTerm()


def _unraisable(previous):
    """A ``sys.unraisablehook`` that delivers again the signal whose exception a finalizer swallowed.

    A signal's handler runs in the main thread between two bytecodes, and that may be inside a
    finalizer (a Dask future's or a connection's ``__del__``, a generator's close) run by the collector:
    Python then prints what the handler raised ("Exception ignored in ...") and goes on, and the
    command would run to its end with exit status 0.  Here the same signal is sent to the main thread
    again a moment later, from another thread, so that its handler runs once the finalizer and this hook
    have returned (in another finalizer, it comes here again; a wait of the main thread's is cut short
    by it, as by the first); any other unraisable exception goes to ``previous``, and a signal whose
    handler runs while it does is sent again as well."""
    main_thread = threading.main_thread()

    def again(signum: int) -> None:
        if sys.unraisablehook is hook:  # main has not returned (its handlers are still set)
            signal.pthread_kill(main_thread.ident, signum)

    def later(e: KeyboardInterrupt) -> bool:
        """Send e's signal to the main thread again in a moment; False if no thread can be started (as the
        interpreter exits: what it stopped is ending anyway)."""
        timer = threading.Timer(0.05, again, (signal.SIGTERM if isinstance(e, SigTerm) else signal.SIGINT,))
        timer.daemon = True
        try:
            timer.start()
        except RuntimeError:
            return False
        return True

    def hook(unraisable) -> None:
        e = unraisable.exc_value
        try:
            if isinstance(e, KeyboardInterrupt) and threading.current_thread() is main_thread and later(e):
                return
            previous(unraisable)
        except KeyboardInterrupt as inside:  # the handler ran in here (printing another one): lost as well
            if threading.current_thread() is not main_thread or not later(inside):
                raise

    return hook


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    # SIGTERM (docker compose stop, systemd, kill) stops a command as Ctrl-C does, rather than ending
    # the process where it stands (a handler only the main thread may set; put back when main returns),
    # and neither is lost in a finalizer
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if main_thread else None
    previous_hook = sys.unraisablehook
    if main_thread:
        sys.unraisablehook = _unraisable(previous_hook)
    try:
        _main(argv)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if main_thread:  # off the main thread main set no hook, and one set meanwhile is not its to undo
            sys.unraisablehook = previous_hook


def _main(argv: list[str]) -> None:
    try:
        cli.main(args=argv or ["--help"], prog_name="packings", standalone_mode=False)
    except Interrupted as e:
        click.echo(f"packings: {e}", err=True)
        sys.exit(e.exit_status)
    except click.exceptions.Abort as e:  # Ctrl-C outside a command's own handling (click printed a newline)
        stopped = _stopped(e.__cause__)
        click.echo(f"packings: {stopped}", err=True)
        sys.exit(stopped.exit_status)
    except click.ClickException as e:
        click.echo(f"packings: error: {e.format_message()}", err=True)
        sys.exit(e.exit_code)
    except PackingsError as e:
        click.echo(f"packings: error: {e}", err=True)
        sys.exit(2 if isinstance(e, UsageError) else 1)
    except Exception as e:  # noqa: BLE001 - only the database's errors are a line; the rest is raised again
        line = _database_error(e)
        if line is None:
            raise
        click.echo(f"packings: error: {line}", err=True)
        sys.exit(1)
    except KeyboardInterrupt as e:
        stopped = _stopped(e)
        click.echo(f"packings: {stopped}", err=True)
        sys.exit(stopped.exit_status)


if __name__ == "__main__":
    main()
