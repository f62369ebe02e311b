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
import sys
import threading
from pathlib import Path

import click

from workers.params import Params

# What this module imports when it is loaded is kept light (no SQLAlchemy, numpy or Dask): `packings
# enumerate` starts the fork server of its local cluster's workers first thing (start_fork_server), and
# every 0.1 s before it is 0.1 s more before the workers can start.  The commands import what they use.

MAX_N = 24  #: beyond this the catalogue cannot be enumerated on any machine (the count grows like (n-5)!)

db_option = click.option(
    "--db", "db_url", default=None, metavar="URL",
    help="Database URL (default: $PACKINGS_DB, else sqlite:///packings.db).",
)


def resolve_url(db_url: str | None) -> str:
    """The database URL to use, with a relative SQLite path made absolute (workers may run elsewhere)."""
    from service.db import default_url, parse_url

    url = parse_url(db_url or default_url())
    if url.get_backend_name() == "sqlite" and url.database and url.database != ":memory:" \
            and not url.database.startswith("file:"):
        url = url.set(database=str(Path(url.database).expanduser().resolve()))
    return url.render_as_string(hide_password=False)


def open_db(db_url: str | None, create: bool = False, migrate: bool = False):
    from service.db import open_database

    return open_database(resolve_url(db_url), create=create, migrate=migrate)


def format_counts(n: int, by_contacts: dict[int, int]) -> str:
    """The paper's table: clusters by number of contacts, relative to 3n - 6."""
    lines = [f"n = {n}: {sum(by_contacts.values())} rigid clusters", f"{'contacts':>10} {'3n-6+':>6} {'clusters':>9}"]
    for m, count in sorted(by_contacts.items()):
        lines.append(f"{m:>10} {m - (3 * n - 6):>+6} {count:>9}")
    return "\n".join(lines)


def check_n(n: int) -> None:
    if n < 4:
        raise click.UsageError(f"n must be at least 4 (got {n}): smaller clusters have no contact triangle to pin")
    if n > MAX_N:
        raise click.UsageError(f"n = {n} is too large: at most {MAX_N} (the number of clusters grows like (n-5)!)")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """Enumerate every rigid cluster of n identical hard spheres."""


@cli.command("enumerate")
@click.argument("n", type=int)
@db_option
@click.option("--workers", "n_workers", type=click.IntRange(1, 512), default=None,
              help="Worker processes of the local Dask cluster (default: one per core).")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Join an existing Dask cluster, e.g. tcp://host:8786, instead of starting one.")
@click.option("--max-break", type=click.IntRange(1, 10), default=None,
              help="Largest number of contacts broken at once (default: no cap, every size up to m - rank + 1 as the "
                   "paper for n <= 14; a cap is for restricted runs of large n).")
@click.option("--min-contacts", type=int, default=None, help="Keep only clusters with at least this many contacts.")
@click.option("--max-attempts", type=click.IntRange(1, 100), default=3, show_default=True,
              help="Tries per expansion before it is marked failed.")
@click.option("--json", "as_json", is_flag=True, help="Print the counts and diagnostics as JSON.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def enumerate_cmd(n: int, db_url: str | None, n_workers: int | None, scheduler: str | None, max_break: int | None,
                  min_contacts: int | None, max_attempts: int, as_json: bool, quiet: bool) -> None:
    """Enumerate the rigid clusters of N spheres into the database and print them by number of contacts.

    Resumes the run with the same N and parameters if the database has one
    (an interrupted run goes on where it stopped; a complete one just prints).
    """
    check_n(n)
    if n_workers is not None and scheduler is not None:
        raise click.UsageError("give either --workers (a local cluster) or --scheduler (an existing one), not both")
    if scheduler is None:
        start_fork_server()  # first: it loads what the local cluster's workers need while the database is opened
    params = Params(max_break=max_break, min_contacts=min_contacts)
    url = resolve_url(db_url)
    from service.db import display_url, parse_url, preflight

    preflight(url)  # a bad URL, server or schema is reported before any Dask cluster starts
    from service.plugin import DatabasePlugin

    # a local cluster starts in the background, its workers warming up with the database plugin, while the
    # database is opened here; .client waits for it
    with _dask_client(scheduler, n_workers, quiet, plugins=(DatabasePlugin(url),)) as dask:
        if scheduler:
            dask.wait()  # an existing scheduler is reached (or that fails, in one line) before the database is touched
        engine = open_db(url, create=True)
        from service.coordinator import run_enumeration

        if scheduler and engine.dialect.name == "sqlite":
            click.echo("packings: warning: SQLite with --scheduler works only if every worker sees this file "
                       f"({engine.url.database}); use PostgreSQL for many machines", err=True)
        bar = _progress_bar(quiet)
        try:
            result = run_enumeration(engine, url, n, params, dask.client, on_progress=None if quiet else bar,
                                     max_attempts=max_attempts)  # quiet: progress is not even read
        finally:
            bar.close()
    engine.dispose()
    gc.freeze()  # what is left is freed by the exit: skip the collector's last pass over it (0.2-0.3 s)
    if as_json:
        click.echo(json.dumps({"n": n, "run": result.run_id, "status": result.status, "total": result.total,
                               "by_contacts": {str(k): v for k, v in result.by_contacts.items()},
                               "diagnostics": result.diagnostics, "seconds": round(result.seconds, 2)}))
    else:
        click.echo(format_counts(n, result.by_contacts))
        click.echo("diagnostics: " + ", ".join(f"{k} {v}" for k, v in result.diagnostics.items()))
        click.echo(f"run {result.run_id}: {result.status} in {result.seconds:.1f} s"
                   + (" (resumed)" if result.resumed else "") + f"; database {display_url(parse_url(url))}")
    for err in result.errors[:10]:
        click.echo(f"packings: failed task: {err}", err=True)
    if result.status == "complete" and not as_json:
        _offer_catalysis(url, n)
    if result.status != "complete":
        raise click.ClickException(f"run {result.run_id} is {result.status}: {len(result.errors)} expansion(s) "
                                   "failed (see `packings status`); rerun the same command to retry them")


def _offer_catalysis(url: str, n: int) -> None:
    """One line when clusters of n + 1 spheres are stored: catalysis may find clusters no path reaches."""
    from service.catalysis import count_stored
    from service.db import make_engine, sessions

    engine = make_engine(url)
    try:
        more = count_stored(sessions(engine, readonly=True), n + 1)
    finally:
        engine.dispose()
    if more:
        click.echo(f"{more} clusters of {n + 1} spheres are stored: `packings catalyse {n}` deletes a sphere from "
                   "each and adds the rigid remainders no path reached")


@cli.command("catalyse")
@click.argument("n", type=int)
@db_option
@click.option("--spheres", "k", type=click.IntRange(1, 10), default=1, show_default=True,
              help="Spheres deleted from each stored cluster of N + K spheres.")
@click.option("--max-break", type=click.IntRange(1, 10), default=None,
              help="As for enumerate (default: no cap): chooses the run of N that the clusters found are added to.")
@click.option("--min-contacts", type=int, default=None,
              help="As for enumerate: keep only remainders with at least this many contacts (and choose that run).")
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def catalyse_cmd(n: int, db_url: str | None, k: int, max_break: int | None, min_contacts: int | None, as_json: bool,
                 quiet: bool) -> None:
    """Delete K spheres from every stored cluster of N + K spheres and add the rigid remainders that are not
    yet stored to the run of N (found_by = catalysis), with an expansion each: `packings enumerate N`
    afterwards follows the paths from them.  Finds clusters no path from the seed reaches (at N = 11 one)."""
    check_n(n)
    check_n(n + k)
    params = Params(max_break=max_break, min_contacts=min_contacts)
    from service.catalysis import NoParents, catalyse, format_report
    from service.db import sessions

    engine = open_db(db_url)
    from tqdm import tqdm

    bar = tqdm(total=0, unit="cluster", desc=f"clusters of {n + k}", file=sys.stderr, disable=quiet or None)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    try:
        report = catalyse(sessions(engine), n, params, spheres=k, on_progress=progress)
    except NoParents as e:
        raise click.ClickException(str(e)) from None
    finally:
        bar.close()
        engine.dispose()
    if as_json:
        click.echo(json.dumps(report.to_dict()))
        return
    click.echo(format_report(report))
    if report.new:
        click.echo(f"run `packings enumerate {n}` to expand them")


#: the modules that the fork server of a local cluster's workers loads before it forks them
FORK_SERVER_PRELOAD = ("distributed", "service.preload")
#: setting this environment variable (spawn, fork, forkserver) chooses how Dask starts local workers
METHOD_ENV = "DASK_DISTRIBUTED__WORKER__MULTIPROCESSING_METHOD"


def start_fork_server() -> bool:
    """Start the process that a local cluster's worker processes are forked from; returns whether they
    will be (it may have been started already: then this does nothing more).

    It starts at once and loads, in the background, what every worker needs (:mod:`service.preload`:
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


def _load_distributed_defaults() -> None:
    """Dask's configuration with distributed's defaults, as ``import distributed`` sets them, but without
    the import (0.3 s, which the fork server's start would wait for): from its ``distributed.yaml``."""
    import importlib.util

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


class _dask_client:
    """A Client on a new LocalCluster, or on an existing scheduler; errors become one line.

    The connection is made in the background from ``__enter__`` on, so that the caller can do its own
    work meanwhile (a local cluster takes a second or two: its scheduler and dashboard start, its worker
    processes are forked from the fork server (:func:`start_fork_server`) once that has loaded what they
    need, and run ``plugins``' setup before it is up); :attr:`client` waits for it.
    """

    def __init__(self, scheduler: str | None, n_workers: int | None, quiet: bool, plugins=()):
        self.scheduler, self.n_workers, self.quiet, self.plugins = scheduler, n_workers, quiet, tuple(plugins)
        self.cluster = self._client = self._error = self._thread = None
        self._announced = False

    def __enter__(self) -> "_dask_client":
        self._thread = threading.Thread(target=self._connect_or_fail, name="packings-dask-start", daemon=True)
        self._thread.start()
        return self

    def _connect_or_fail(self) -> None:
        try:
            self._connect()
        except BaseException as e:  # noqa: BLE001 - raised again by .client, in the caller's thread
            self._error = e

    def _connect(self) -> None:
        import dask
        from distributed import Client, LocalCluster

        for name in ("distributed", "bokeh", "tornado"):
            logging.getLogger(name).setLevel(logging.ERROR)
        if self.scheduler:
            try:
                self._client = Client(self.scheduler, timeout="10s")
            except (OSError, TimeoutError, ValueError) as e:
                raise click.ClickException(f"cannot reach the Dask scheduler at {self.scheduler}: "
                                           f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
        else:
            k = self.n_workers or os.cpu_count() or 1
            if PROFILE_ENV not in os.environ:
                # Dask's statistical profiler samples each worker's stack every 10 ms: 8 % of a run's time
                # at n = 11 (the dashboard's Profile page is empty without it; the variable turns it back on)
                dask.config.set({"distributed.worker.profile.enabled": False})
            start_fork_server()  # if `packings enumerate` has not yet
            # the plugins are set up in each worker process before it joins (later ones: client.register_plugin)
            self.cluster = LocalCluster(n_workers=k, threads_per_worker=1, processes=True, host="127.0.0.1",
                                        dashboard_address="127.0.0.1:8787", silence_logs=logging.ERROR,
                                        plugins=self.plugins)
            self._client = Client(self.cluster)

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
            where = self.scheduler or f"local cluster, {len(self._client.nthreads())} worker processes"
            click.echo(f"dask: {where}; dashboard {self._client.dashboard_link}", err=True)
            self._announced = True
        return self._client

    def __exit__(self, *exc):
        if self._thread is not None:
            self._thread.join()
        if self._client is not None:
            self._client.close()
        if self.cluster is not None:
            self.cluster.close()
        return False


def _progress_bar(quiet: bool):
    from tqdm import tqdm

    bar = tqdm(total=0, unit="exp", desc="expansions", file=sys.stderr, disable=quiet, dynamic_ncols=True)

    def update(p):
        bar.total = p.total
        bar.n = p.done
        bar.set_postfix_str(f"pending {p.pending + p.leased}, clusters {p.clusters}"
                            + (f", failed {p.failed}" if p.failed else ""), refresh=False)
        bar.refresh()

    update.close = bar.close  # type: ignore[attr-defined]
    return update


@cli.group("db")
def db_group() -> None:
    """The database schema (Alembic migrations)."""


@db_group.command("upgrade")
@db_option
def db_upgrade(db_url: str | None) -> None:
    """Create the schema, or migrate it to this code's version."""
    from service.db import current_revision, display_url, head_revision

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

    from service import store
    from service.db import sessions

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
    from service.db import connect_error, current_revision, head_revision, make_engine

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
    """Runs and their frontier (expansions pending, leased, done, failed)."""
    from sqlalchemy import select

    from service import store
    from service.db import sessions
    from service.models import Run

    engine = open_db(db_url)
    rows = []
    with sessions(engine, readonly=True)() as s:
        for run in s.execute(select(Run).order_by(Run.id)).scalars():
            f = store.frontier(s, run.id)
            params = json.loads(run.params)
            rows.append({"run": run.id, "n": run.n, "status": run.status, "clusters": sum(f.values()),
                         "pending": f.get("pending", 0), "leased": f.get("leased", 0), "done": f.get("done", 0),
                         "failed": f.get("failed", 0), "max_break": params.get("max_break"),
                         "min_contacts": params.get("min_contacts"), "seconds": round(run.seconds or 0.0, 1),
                         "started": run.started_at.isoformat(timespec="seconds"),
                         "coordinator": run.coordinator})
    engine.dispose()
    if as_json:
        click.echo(json.dumps(rows))
        return
    if not rows:
        click.echo("no runs yet: `packings enumerate N` starts one")
        return
    cols = ["run", "n", "status", "clusters", "pending", "leased", "done", "failed", "max_break", "seconds", "started"]
    click.echo(_export.table(cols, [[r[c] for c in cols] for r in rows]))


@cli.command("stats")
@db_option
@click.option("--n", "n", type=int, default=None, help="Only this n.")
@click.option("--json", "as_json", is_flag=True, help="A JSON list with one object per n.")
def stats_cmd(db_url: str | None, n: int | None, as_json: bool) -> None:
    """What the catalogue contains, per n, in the paper's style.

    Clusters, singular clusters and close-packed fragments by number of
    contacts; fragments by lattice; adjacency matrices with several
    geometries; the smallest gaps; paths and circular paths; the fit of the
    totals to b·(n−5)!."""
    from service.db import sessions
    from service.stats import fit_all, format_fit, format_stats, stats
    from service.store import counts_by_n

    engine = open_db(db_url)
    with sessions(engine, readonly=True)() as s:
        every = counts_by_n(s)
        rows, fit = stats(s, n, every), fit_all(every)
    engine.dispose()
    if as_json:
        click.echo(json.dumps(rows))
        return
    if not rows:
        click.echo("no clusters" + (f" with n = {n}" if n is not None else ""))
        return
    click.echo("\n\n".join(format_stats(r) for r in rows) + "\n\n" + format_fit(fit))



@cli.command("audit")
@db_option
@click.option("--n", "n", type=int, default=None, help="Only this n.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object: the three lists and the tolerances.")
def audit_cmd(db_url: str | None, n: int | None, as_json: bool) -> None:
    """Look for junk clusters: (a) clusters with a non-contact pair within tol_a0 of touching, and what
    adding the pair gives (a stored cluster: a near copy of it); (b) pre-stress margins within a factor
    of 10 of tol_psd; (c) two geometries of one contact graph within 100 tol_d.  A clean catalogue has
    (a) and (c) empty.  Exits 0 whatever it finds (it is a report)."""
    from service.audit import audit, format_audit
    from service.db import sessions

    engine = open_db(db_url)
    try:
        with sessions(engine, readonly=True)() as s:
            report = audit(s, n)
    finally:
        engine.dispose()
    click.echo(json.dumps(report.to_dict()) if as_json else format_audit(report))


# --------------------------------------------------------------------------- queries: select, show, export

from service import export as _export  # noqa: E402 - the query commands' formats

_SELECTION_HELP = ("SELECTION is comma-separated terms, all of which must hold: key (a boolean key is true), "
                   "!key or 'not key' (false), key OP value with OP one of = != < <= > >=; e.g. "
                   "'n=10,contacts<24,singular', '!singular,min_gap>0.1', hyperstatic, run=1.  Keys:\n\n\b\n")


class _SelectionCommand(click.Command):
    """A command taking a SELECTION, whose help ends with the selection's keys (built when the help is
    shown: they come from service.selection, which loads SQLAlchemy)."""

    def format_epilog(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        from service.selection import describe_keys

        self.epilog = _SELECTION_HELP + describe_keys()
        super().format_epilog(ctx, formatter)
_TABLE_COLUMNS = ["id", "n", "contacts", "embedding", "singular", "flexes", "stresses", "min_gap", "lattice",
                  "certificate"]


def _query(selection: str | None, **kw):
    """The SELECT for a selection; a bad one is a usage error (checked before the database is opened)."""
    from service.selection import SelectionError, query

    try:
        return query(selection, **kw)
    except SelectionError as e:
        raise click.UsageError(str(e)) from None


class _reading:
    """A session on an existing database, disposed of afterwards."""

    def __init__(self, db_url: str | None):
        self.engine = open_db(db_url)

    def __enter__(self):
        from service.db import sessions

        self.session = sessions(self.engine, readonly=True)()
        return self.session

    def __exit__(self, *exc):
        self.session.close()
        self.engine.dispose()
        return False


def _echo_chunks(chunks) -> None:
    for chunk in chunks:
        click.echo(chunk, nl=False)


def _table_row(f: dict) -> list:
    cert = f["certificate"]
    return [f["id"], f["n"], f["contacts"], f["embedding"], f["singular"], f["flexes"], f["stresses"],
            None if f["min_gap"] is None else f"{f['min_gap']:.6g}", f["lattice"], cert if len(cert) <= 16 else cert[:13] + "..."]


@cli.command("select", cls=_SelectionCommand)
@click.argument("selection", required=False, default="")
@db_option
@click.option("--json", "as_json", is_flag=True, help="A JSON list: every fact, coords and contact_list.")
@click.option("--csv", "as_csv", is_flag=True, help="CSV with a header line (no coordinates).")
@click.option("--count", "as_count", is_flag=True, help="Only the number of clusters selected.")
@click.option("--limit", type=click.IntRange(min=0), default=None, help="At most this many clusters.")
@click.option("--sort", default=None, metavar="KEY", help="Sort by KEY (-KEY: descending); default n, contacts, id.")
def select_cmd(selection: str, db_url: str | None, as_json: bool, as_csv: bool, as_count: bool, limit: int | None,
               sort: str | None) -> None:
    """The stored clusters that match SELECTION (default: all), as a table, JSON or CSV."""
    if as_json + as_csv + as_count > 1:
        raise click.UsageError("give at most one of --json, --csv, --count")
    q = _query(selection, sort=sort, limit=limit)
    with _reading(db_url) as s:
        if as_count:
            from sqlalchemy import func, select

            click.echo(s.execute(select(func.count()).select_from(q.order_by(None).subquery())).scalar_one())
            return
        rows = s.execute(q.execution_options(yield_per=500)).scalars()
        if as_json:
            _echo_chunks(_export.to_json(_export.record(c) for c in rows))
        elif as_csv:
            _echo_chunks(_export.to_csv(_export.facts(c) for c in rows))
        else:
            table = [_table_row(_export.facts(c)) for c in rows]
            click.echo(_export.table(_TABLE_COLUMNS, table) + f"\n{len(table)} clusters" if table else "no clusters match")


@cli.command("show")
@click.argument("cluster_id", metavar="ID", type=int)
@db_option
@click.option("--json", "as_json", is_flag=True, help="One JSON object.")
def show_cmd(cluster_id: int, db_url: str | None, as_json: bool) -> None:
    """Cluster ID in full: every fact, the exact coordinates, the contacts, the
    paths leaving and reaching it, and the runs whose frontier holds it."""
    from service.selection import links, query

    with _reading(db_url) as s:
        c = s.execute(query(f"id={cluster_id}")).scalar_one_or_none()
        if c is None:
            raise click.ClickException(f"no cluster with id {cluster_id}")
        rec, info = _export.record(c), links(s, cluster_id)
    if as_json:
        click.echo(json.dumps({**rec, **info}))
        return
    out = [f"cluster {rec['id']}: n = {rec['n']}, {rec['contacts']} contacts (3n-6{rec['excess']:+d}, {rec['static']})"]
    out += [f"  {k:<13} {'' if rec[k] is None else repr(rec[k]) if isinstance(rec[k], float) else rec[k]}"
            for k in _export.FACTS]
    out += ["coordinates (unit: sphere diameter):",
            _export.table(["i", "x", "y", "z"], [[i, *map(repr, x)] for i, x in enumerate(rec["coords"])])]
    pairs = [f"{i}-{j}" for i, j in rec["contact_list"]]
    out += [f"contacts ({len(pairs)}):"] + ["  " + " ".join(pairs[k:k + 12]) for k in range(0, len(pairs), 12)]
    by = ", ".join(f"{o} {c}" for o, c in info["leaving_by_outcome"].items())
    out += [f"paths leaving: {info['paths_leaving']}" + (f" ({by})" if by else ""),
            f"paths reaching: {info['paths_reaching']} from {info['reached_from']} clusters"]
    out += [f"run {r['run']} (n = {r['n']}, {r['run_status']}): expansion {r['expansion']}"
            + ("" if r["paths"] is None else f", {r['paths']} paths") for r in info["runs"]] or ["in no run's frontier"]
    click.echo("\n".join(out))


@cli.command("export", cls=_SelectionCommand)
@click.argument("selection", required=False, default="")
@click.option("--n", "n", type=int, default=None, help="Only clusters of N spheres.")
@click.option("--format", "fmt", type=click.Choice(_export.FORMATS), default=None,
              help="Default: from the suffix of -o (.extxyz, .xyz, .json), else extxyz.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write to this file (replaced whole, never half-written); default standard output.")
@db_option
def export_cmd(selection: str, n: int | None, fmt: str | None, output: str | None, db_url: str | None) -> None:
    """Write the clusters that match SELECTION (default: all), ordered by n, contacts, id: extended XYZ
    (readable by ase.io.read), plain XYZ, or JSON with every fact, coordinates and contacts."""
    fmt = fmt or _export.format_for(output)
    q = _query(selection, n=n)
    written = 0
    with _reading(db_url) as s:
        def records():
            nonlocal written
            for c in s.execute(q.execution_options(yield_per=500)).scalars():
                written += 1
                yield _export.record(c)

        chunks = _export.render(fmt, records())
        if output is None:
            _echo_chunks(chunks)
            return
        try:
            _export.write_atomic(output, chunks)
        except OSError as e:
            raise click.ClickException(f"cannot write {output}: {e.strerror or e}") from None
    click.echo(f"wrote {written} clusters ({fmt}) to {output}")


from service.plots import plot as _plot  # noqa: E402 - its own module; imports matplotlib only when it draws

cli.add_command(_plot)


def _database_error(e: Exception) -> str | None:
    """The one line for a database's error (service.db.DatabaseError: one a user can fix; SQLAlchemy's:
    e.g. the server went away mid-command, and transactions rolled back), None for any other error."""
    from sqlalchemy.exc import SQLAlchemyError

    from service.db import DatabaseError, first_line

    if isinstance(e, DatabaseError):
        return str(e)
    if isinstance(e, SQLAlchemyError):
        return f"database: {first_line(e)}"
    return None


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    try:
        cli.main(args=argv or ["--help"], prog_name="packings", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as e:
        click.echo(f"packings: error: {e.format_message()}", err=True)
        sys.exit(e.exit_code)
    except Exception as e:  # noqa: BLE001 - only the database's errors are a line; the rest is raised again
        line = _database_error(e)
        if line is None:
            raise
        click.echo(f"packings: error: {line}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        click.echo("packings: interrupted; rerun the same command to resume", err=True)
        sys.exit(130)


if __name__ == "__main__":
    main()
