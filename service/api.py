"""The Python API, the way ``ase.db.connect`` works: :func:`connect` opens a
catalogue (the run driver, ``packings.enumerate``, is :mod:`packings.service.run`'s).

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
runs): the command line loads it (:func:`resolve_url`) before ``packings enumerate``
starts its workers' fork server.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any, Iterator

from packings.service.errors import NotFound, UsageError
from packings.service.export import ase_info, facts

if TYPE_CHECKING:
    import numpy as np

# SQLAlchemy, numpy, ASE (optional) and the modules that load them (the database, the selection
# language, the store, the reports, the numerics) are imported by the functions that use them, so that
# loading this module stays light (module doc).


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

        from packings.service import queries
        from packings.service.models import Run

        out = []
        with self.session() as s:
            for run in s.execute(select(Run).order_by(Run.id)).scalars():
                f = queries.frontier(s, run.id)
                faults = queries.faults(s, run.id)
                params = json.loads(run.params)
                out.append(
                    {
                        "run": run.id,
                        "n": run.n,
                        "status": queries.shown_status(run),
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
