"""The Python API, the way ``ase.db.connect`` works: :func:`connect` opens a
catalogue, :func:`enumerate` runs or resumes a run.

    import packings
    cat = packings.connect("sqlite:///packings.db")
    for row in cat.select("n=10,contacts=24", sort="-min_gap", limit=3):
        print(row.id, row.lattice, row.min_gap, row.coords.shape)
    atoms = cat.get(1).to_atoms()

The command line (:mod:`packings.service.cli`) is a thin layer over this module: the
selection language is :mod:`packings.service.selection`'s, the facts of a cluster are
:mod:`packings.service.export`'s, and the errors a user can cause are
:mod:`packings.service.errors`' (one line each), whichever way the catalogue is used.

Loading this module is light (no SQLAlchemy, numpy or Dask until a function
runs): ``import packings`` must stay cheap for every Dask worker.
"""

from __future__ import annotations

import json
import os
import sys
from typing import TYPE_CHECKING, Any, Callable, Iterator

from packings.service.dask_cluster import DASHBOARD_ADDRESS
from packings.service.errors import NotFound, UsageError
from packings.service.validate import check_run

if TYPE_CHECKING:
    import numpy as np

    from packings.service.coordinator import RunResult


def resolve_url(url: str | None) -> str:
    """The database URL to use: ``url``, else ``$PACKINGS_DB``, else ``sqlite:///packings.db``; a bare
    file name ending in .db is a SQLite file, and a relative SQLite path is made absolute (workers may
    run in another directory)."""
    from packings.service.db import absolute, default_url, parse_url

    return absolute(parse_url(url or default_url())).render_as_string(hide_password=False)


# --------------------------------------------------------------------------- rows


class Row:
    """One stored cluster.

    Its facts (:data:`packings.service.export.FACTS`: ``id``, ``n``, ``embedding``,
    ``lattice``, ``min_gap``, ``singular``, ...) are attributes and the dict
    :attr:`facts`.  ``coords`` is the ``(n, 3)`` float64 array of the centres
    (unit: the sphere diameter), bit for bit as stored; ``contacts`` is the
    ``(m, 2)`` int array of contact pairs, so the number of contacts is
    ``len(row.contacts)`` (also ``row.facts["contacts"]``).
    """

    __slots__ = ("facts", "coords", "contacts")

    def __init__(self, facts: dict, coords: np.ndarray, contacts: np.ndarray):
        self.facts, self.coords, self.contacts = facts, coords, contacts

    @classmethod
    def from_model(cls, c) -> Row:
        """The row of a :class:`packings.service.models.ClusterRow`."""
        import numpy as np

        from packings.service.export import facts

        coords = np.frombuffer(c.coords, dtype="<f8").reshape(c.n, 3).astype(np.float64)
        contacts = np.array(json.loads(c.contact_list), dtype=np.int64).reshape(-1, 2)
        return cls(facts(c), coords, contacts)

    def __getattr__(self, name: str) -> Any:
        try:
            return self.facts[name]
        except KeyError:
            raise AttributeError(f"a cluster row has no fact {name!r}") from None

    def __dir__(self):
        return [*super().__dir__(), *self.facts]

    def __repr__(self) -> str:
        return (
            f"<Row {self.facts['id']}: n={self.facts['n']}, {len(self.contacts)} contacts, "
            f"embedding {self.facts['embedding']}>"
        )

    def record(self) -> dict:
        """Facts, ``coords`` (lists of floats) and ``contact_list`` (pairs): a JSON record, as
        ``packings select --json`` prints it."""
        return {**self.facts, "coords": self.coords.tolist(), "contact_list": self.contacts.tolist()}

    def exact(self):
        """What Kantorovich's theorem proves of this cluster's coordinates
        (:class:`packings.workers.exact.Exact`: a root of its contact equations within ``radius``, its
        smallest gap there at least ``gap``), or None for a cluster with a flex, whose rigidity rests
        on the pre-stress test instead (docs/method.md)."""
        if self.facts["flexes"]:
            return None
        from packings.workers.cluster import Cluster
        from packings.workers.exact import exact_cluster

        return exact_cluster(Cluster(self.coords, tuple(map(tuple, self.contacts.tolist()))))

    def to_atoms(self):
        """The cluster as an :class:`ase.Atoms` (every sphere the dummy element ``X``), with its facts in
        ``info`` (those that are not None; ``id`` and ``stresses``, which ASE's database reserves, as
        ``cluster_id`` and ``self_stresses``) and the contact pairs in ``info["contact_pairs"]``."""
        try:
            from ase import Atoms
        except ImportError:
            raise ImportError("Row.to_atoms() needs ASE, which is not installed: pip install ase") from None
        from packings.service.export import ase_info

        info = ase_info(self.facts)
        info["contact_pairs"] = self.contacts.copy()
        return Atoms(symbols=["X"] * len(self.coords), positions=self.coords.copy(), info=info)


# --------------------------------------------------------------------------- the catalogue


def connect(url: str | None = None, *, create: bool = False) -> Catalogue:
    """The catalogue in the database at ``url`` (default: ``$PACKINGS_DB``, else
    ``sqlite:///packings.db``; a bare ``name.db`` is a SQLite file).

    A database that is missing or empty is refused unless ``create`` (then an empty
    catalogue is made), and one with another schema is refused with the command that
    migrates it: :class:`packings.service.errors.PackingsError`, one line, nothing written.
    """
    return Catalogue(url, create=create)


def _value_text(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return "none" if v is None else str(v)


def selection_query(selection: str | None, equalities: dict | None = None, **kw):
    """The SELECT of a selection and ``key=value`` equalities, with ``sort``/``limit`` as
    :func:`packings.service.selection.query`; a bad one raises :class:`packings.service.errors.UsageError` (no database
    is needed to check it)."""
    from packings.service.selection import parse, parse_term, query

    terms = parse(selection) + [parse_term(f"{k}={_value_text(v)}") for k, v in (equalities or {}).items()]
    return query(terms, **kw)


class Catalogue:
    """A connection to a packings database (:func:`connect`).  Use it as a context manager, or call
    :meth:`close`; every method reads in its own transaction, so a catalogue may be read while a run
    writes to it."""

    def __init__(self, url: str | None = None, *, create: bool = False):
        from packings.service.db import open_database

        self.url = resolve_url(url)
        self.engine = open_database(self.url, create=create)

    def __repr__(self) -> str:
        from packings.service.db import display_url

        return f"<packings catalogue {display_url(self.engine.url)}>"

    def __enter__(self) -> Catalogue:
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False

    def close(self) -> None:
        self.engine.dispose()

    def session(self):
        """A read-only SQLAlchemy session on the database, for queries of your own (the tables are
        :mod:`packings.service.models`'; ``with cat.session() as s: ...``)."""
        from packings.service.db import sessions

        return sessions(self.engine, readonly=True)()

    def select(
        self, selection: str | None = "", *, sort: str | None = None, limit: int | None = None, **equalities
    ) -> Iterator[Row]:
        """The clusters that match ``selection`` (the command line's language, e.g. ``"n=10,contacts<24,
        singular"``) and every ``key=value`` given, as :class:`Row` objects, ordered by ``sort`` (a key,
        ``-key`` for descending; default n, contacts, id), at most ``limit`` of them (None: all).  A bad
        selection raises :class:`packings.service.errors.UsageError` here, not when the rows are read."""
        if limit is not None and limit < 0:
            raise UsageError(f"limit must be at least 0 (got {limit})")
        q = selection_query(selection, equalities, sort=sort, limit=limit)
        return self._rows(q)

    def _rows(self, q) -> Iterator[Row]:
        with self.session() as s:
            for c in s.execute(q.execution_options(yield_per=500)).scalars():
                yield Row.from_model(c)

    def count(self, selection: str | None = "", **equalities) -> int:
        """How many clusters match (as :meth:`select`)."""
        from sqlalchemy import func, select

        q = selection_query(selection, equalities)
        with self.session() as s:
            return s.execute(select(func.count()).select_from(q.order_by(None).subquery())).scalar_one()

    def get(self, id: int) -> Row:
        """Cluster ``id``; :class:`packings.service.errors.NotFound` (a KeyError) if there is none."""
        rows = list(self.select(f"id={int(id)}"))
        if not rows:
            raise NotFound(f"no cluster with id {id}")
        return rows[0]

    def links(self, id: int) -> dict:
        """What the database holds about cluster ``id`` besides its row: the paths leaving it (by
        outcome), the paths reaching it and from how many clusters, and the runs whose frontier holds it."""
        from packings.service.queries import links

        self.get(id)
        with self.session() as s:
            return links(s, int(id))

    def transitions(self, id: int, *, reaching: bool = False) -> list[dict]:
        """The transitions from cluster ``id`` (its paths: followed, by symmetry or retraced, and the
        attempts no path came of; or, if ``reaching``, those that ended at it), in the order they were
        written, one dict each: ``attempt`` (its place among its expansion's attempts), ``run``,
        ``source``, ``broken`` (the contact pairs broken), ``direction`` (+1 or -1 along the path's
        tangent, 0 if no path was followed), ``outcome``, ``target`` (the cluster reached, None if none
        is stored), ``steps`` and ``new_contacts`` (the pairs formed at the endpoint)."""
        from packings.service.queries import transitions

        self.get(id)
        with self.session() as s:
            return [
                {
                    "attempt": t.attempt,
                    "run": t.run_id,
                    "source": t.source_id,
                    "broken": [list(p) for p in t.broken],
                    "direction": t.direction,
                    "outcome": t.outcome,
                    "target": t.target_id,
                    "steps": t.steps,
                    "new_contacts": [list(p) for p in t.new_contacts],
                }
                for t in (transitions(s, target=int(id)) if reaching else transitions(s, source=int(id)))
            ]

    def stats(self, n: int | None = None) -> list[dict]:
        """What the catalogue holds, one dict per n (all n, or only ``n``): what ``packings stats --json``
        prints."""
        from packings.service.queries import counts_by_n
        from packings.service.stats import stats

        with self.session() as s:
            return stats(s, n, counts_by_n(s))

    def probabilities(self, n: int, kappa: float, width: float | None = None) -> dict:
        """The equilibrium probability of each stored cluster of n and of each number of contacts at sticky
        parameter ``kappa``: in the sticky limit Z = κ^m z, or with ``width`` the leading term of a square
        well that wide (needed from n = 9, where a singular cluster's Z is not κ^m z).  A dict with
        ``by_contacts`` ({m: probability}) and ``clusters`` (id, contacts, probability; most probable
        first); :class:`packings.PackingsError` saying why where some cluster has no value
        (:mod:`packings.service.probabilities`)."""
        from packings.service.probabilities import probabilities

        with self.session() as s:
            return probabilities(s, n, kappa, width)

    def network(self, n: int):
        """The network of the stored clusters of n and the paths between them, a ``networkx.DiGraph``: nodes
        are cluster ids with their facts, edges carry ``paths`` (multiplicity), ``steps`` (the fewest),
        ``broken`` (JSON) and, on a self-loop, ``circular`` and ``rearranged``
        (:mod:`packings.service.network`)."""
        from packings.service.network import network

        with self.session() as s:
            return network(s, n)

    def fit(self) -> dict | None:
        """The fit of the totals to b·(n−5)!, the n held only by runs restricted by --min-contacts and those
        no full run has completed left out (None if no n is left)."""
        from packings.service.queries import counts_by_n, incomplete_ns
        from packings.service.stats import fit_all

        with self.session() as s:
            return fit_all(counts_by_n(s), *incomplete_ns(s))

    def runs(self) -> list[dict]:
        """Every run with its frontier, one dict each: what ``packings status --json`` prints.  A run
        marked running whose coordinator is gone is shown as ``interrupted``; ``retries`` counts the
        expansions put back after an infrastructure fault (uncounted), ``isolated_failures`` the tasks
        of one expansion alone lost again (each an attempt)."""
        from sqlalchemy import select

        from packings.service import store
        from packings.service.models import Run

        out = []
        with self.session() as s:
            for run in s.execute(select(Run).order_by(Run.id)).scalars():
                f = store.frontier(s, run.id)
                faults = store.faults(s, run.id)
                params = json.loads(run.params)
                out.append(
                    {
                        "run": run.id,
                        "n": run.n,
                        "status": store.shown_status(run),
                        "clusters": sum(f.values()),
                        "pending": f.get("pending", 0),
                        "leased": f.get("leased", 0),
                        "done": f.get("done", 0),
                        "failed": f.get("failed", 0),
                        "retries": faults["retries"],
                        "isolated_failures": faults["isolated_failures"],
                        "max_break": params.get("max_break"),
                        "min_contacts": params.get("min_contacts"),
                        "seconds": round(run.seconds or 0.0, 1),
                        "started": run.started_at.isoformat(timespec="seconds"),
                        "coordinator": run.coordinator,
                    }
                )
        return out


# --------------------------------------------------------------------------- running


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

    from packings.service.owners import busy

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
    """Enumerate the rigid clusters of ``n`` spheres into the database at ``url`` (as :func:`connect`;
    created if need be), or resume the run with the same n and parameters, and return its result:
    ``status`` ("complete" or "incomplete"), ``by_contacts``, ``total``, ``diagnostics``, ``seconds``,
    ``resumed``, ``errors`` (:class:`packings.service.coordinator.RunResult`).

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
    from packings.service.dask_cluster import RECONNECT_ENV, RECONNECT_SECONDS, dask_client, start_fork_server
    from packings.workers.params import Params

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
        from packings.service.slurm import check_options

        slurm = check_options(slurm)
    local = scheduler is None and slurm is None
    compiling = False
    if local or slurm is not None:
        from packings.workers.kernel_cache import kernels_cached

        compiling = kernels_cached() is False  # then the fork server (or this process, for Slurm) compiles them
    if local:
        start_fork_server()  # first: it loads what the local cluster's workers need while the database is opened
    # a local cluster that has had no worker for this long cannot start them again: stop, resumably
    # (an existing cluster's workers may join later, and Slurm's jobs may wait in its queue: wait for them)
    workerless = _seconds(WORKERLESS_ENV, LOCAL_WORKERLESS_SECONDS) if local else None
    reconnect = _seconds(RECONNECT_ENV, RECONNECT_SECONDS)
    params = Params(max_break=max_break, min_contacts=min_contacts)
    if min_contacts is not None:  # a run restricted so starts from a cluster with that many contacts
        from packings.workers.seeds import seed_cluster

        try:
            seed_cluster(n, params)
        except ValueError as e:
            raise UsageError(str(e)) from None
    url = resolve_url(url)
    if slurm is not None:
        from packings.service.slurm import require_sbatch

        _refuse_sqlite_for_slurm(url)
        require_sbatch()
    from packings.service.db import open_database, preflight

    # a bad URL, server or schema, or a run that another live coordinator holds, is reported before any
    # Dask cluster starts
    preflight(url, check=lambda engine: _refuse_busy_run(engine, n, params))
    if compiling:  # said, rather than a silent minute
        print(
            "packings: compiling the numerical kernels, once for this installation (about a minute on two "
            "cores; later runs load them in a second)",
            file=sys.stderr,
            flush=True,
        )
        if slurm is not None:  # here, once, into the cache the jobs load them from, rather than in every job
            from packings.workers.kernel_cache import compile_apart

            compile_apart()
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
            from packings.service.coordinator import run_enumeration

            if scheduler is not None and engine.dialect.name == "sqlite":
                print(
                    "packings: warning: SQLite with a scheduler works only if every worker sees this file "
                    f"({engine.url.database}); use PostgreSQL for many machines",
                    file=sys.stderr,
                )

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
                    engine, url, n, params, result.run_id, dask.client, progress, before=dask.fresh_workers
                )
                if report is None:
                    break
                passes.append(report)
                if not report.expansions_added:
                    break
                result = paths()
            result.catalysis = passes
            return result
        finally:
            engine.dispose()


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


def _glued_pass(engine, url: str, n: int, params, run_id: int, client, progress: bool, before=None):
    """A glued catalysis pass into ``run_id`` over the clusters of n stored since the passes before it
    (:func:`packings.service.catalysis.covered`), on ``client``'s workers; its report, or None if there are none.
    ``before()`` is called first when there is a pass to make (``packings enumerate`` gives its local
    workers fresh processes there, so that a pass's record of the remainders seen is not added on top of
    what the paths left in them)."""
    from packings.service.catalysis import catalyse, count_stored, covered
    from packings.service.db import sessions
    from packings.service.plugin import plugin_name

    Session_ = sessions(engine)
    after = covered(Session_, run_id)
    if not count_stored(Session_, n, after):
        return None
    if before is not None:
        before()
    bar, shown = pass_bar(f"clusters of {n} (glued)", "cluster", not progress, off_terminal=True)
    try:
        return catalyse(
            Session_, n, params, glued=True, client=client, plugin=plugin_name(url), after=after, on_progress=shown
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
