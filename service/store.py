"""Transactions on the database: runs, the frontier, and write-back of results.

Every function here is one transaction, or a read of its tasks' inputs; the reads of the catalogue and
of a run's state (its frontier, faults and counts) are :mod:`packings.service.queries`.  The
rules that make the service safe under concurrency and failure:

* Claims: a batch of pending expansions becomes ``leased`` with a fresh token
  (PostgreSQL: ``SELECT ... FOR UPDATE SKIP LOCKED``; SQLite: the transaction
  begins IMMEDIATE, so claims are serial, and SQLAlchemy's SQLite dialect
  leaves ``FOR UPDATE`` out of every statement here).
* Write-back (:func:`record_expansions`): one transaction per task inserts
  the new clusters of its expansions, their pending expansions and their
  attempts (one packed row per expansion, and the clusters it reached: edges), and marks the expansions done, each only if it is still leased
  with the token the task was given (its first statement marks it done on that
  condition; if it matches no row, nothing of it is written).  A task run
  twice therefore changes nothing the second time, and a task that dies
  writes nothing.  It runs Core statements built once (:data:`_TASKS` ...), as a task
  runs them for every expansion.
* Deduplication: before comparing an endpoint with the stored clusters of its
  certificate, the transaction takes ``pg_advisory_xact_lock`` on (n,
  certificate) (PostgreSQL; locks taken in sorted order, so two tasks cannot
  deadlock) or already holds SQLite's write lock.
"""

from __future__ import annotations

import functools
import json
import math
import uuid
from dataclasses import dataclass, field, replace
from importlib import metadata
from typing import TYPE_CHECKING, Iterable

import numpy as np
from sqlalchemy import Connection, bindparam, case, func, insert, literal_column, select, update
from sqlalchemy.orm import Session, sessionmaker

from packings.service.db import READONLY, insert_many, transaction_locks
from packings.service.models import (
    COMPLETE,
    DONE,
    FAILED,
    FOUND_PATH,
    FOUND_SEED,
    INCOMPLETE,
    LEASED,
    NOT_CLOSE_PACKED,
    PENDING,
    RUNNING,
    AttemptsRow,
    ClusterRow,
    Edge,
    ExpansionRow,
    Run,
    core_cluster,
    format_pairs,
    remember_core_cluster,
    utcnow,
)
from packings.service.owners import busy
from packings.service.paths_codec import Attempt, pack, summary
from packings.service.queries import arrivals_at, frontier
from packings.workers.classify import lattice_type
from packings.workers.cluster import Cluster as CoreCluster
from packings.workers.free_energy import free_energy
from packings.workers.identity import alignment, certificate_key, embedding_position, find_match
from packings.workers.outcomes import CIRCULAR, REARRANGED
from packings.workers.params import Params
from packings.workers.rigidity import Rigidity, rigidity
from packings.workers.seeds import seed_cluster

if TYPE_CHECKING:  # the coordinator, which imports this module, never loads the path-following code
    from packings.workers.expand import Expansion as CoreExpansion


def code_version() -> str:
    try:
        return metadata.version("packings")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare checkout
        return "unknown"


def contacts_json(pairs) -> str:
    """``[[i, j], ...]`` exactly as ``json.dumps`` writes it (the contact list of every cluster a write-back
    compares or stores: the contacts given as tuples are remembered)."""
    if isinstance(pairs, tuple):
        try:
            return _contacts_json(pairs)
        except TypeError:  # not hashable
            pass
    return format_pairs(pairs)


_contacts_json = functools.lru_cache(maxsize=65536)(format_pairs)


# --------------------------------------------------------------------------- statements

# The statements a task runs for every expansion, built once: building one costs about as much as
# running it on SQLite.  Core statements on the tables, so that no ORM object is made per row.
_E, _C, _R = ExpansionRow.__table__, ClusterRow.__table__, Run.__table__
_A, _EDGES = AttemptsRow.__table__, Edge.__table__
_TASKS = (
    select(
        _E.c.id,
        _E.c.status,
        _E.c.lease_token,
        _E.c.run_id,
        _E.c.cluster_id,
        _C.c.n,
        _C.c.coords,
        _C.c.contact_list,
        _R.c.params,
    )
    .join_from(_E, _C, _C.c.id == _E.c.cluster_id)
    .join(_R, _R.c.id == _E.c.run_id)
    .where(_E.c.id.in_(bindparam("eids", expanding=True)))
)
_STORED = (
    select(_C.c.id, _C.c.certificate, _C.c.embedding, _C.c.coords, _C.c.contact_list, _C.c.found_in_run)
    .where(_C.c.n == bindparam("n"), _C.c.certificate.in_(bindparam("certs", expanding=True)))
    .order_by(_C.c.certificate, _C.c.embedding)
)
_HAVE_EXPANSIONS = select(_E.c.cluster_id).where(
    _E.c.run_id == bindparam("run"), _E.c.cluster_id.in_(bindparam("ids", expanding=True))
)
_INSERT_CLUSTER = insert(_C)
_RENUMBER = update(_C).where(_C.c.id == bindparam("cid")).values(embedding=bindparam("new_embedding"))
_INSERT_EXPANSION = insert(_E)
#: an attempts row's values, in this order, and an edge's (see :func:`insert_attempts`)
ATTEMPTS_COLUMNS = ("run_id", "source_id", "attempts", "paths", "circular", "rearranged", "data")
EDGE_COLUMNS = ("target_id", "source_id", "run_id", "paths", "labelled")
#: an expansion done, if still leased with the token (SET: the columns given when it runs)
_DONE = update(_E).where(_E.c.id == bindparam("eid"), _E.c.status == LEASED, _E.c.lease_token == bindparam("token"))


# --------------------------------------------------------------------------- clusters


def lattice_value(c: CoreCluster) -> str:
    """clusters.lattice of a cluster: its close-packed lattice, or :data:`NOT_CLOSE_PACKED`."""
    return lattice_type(c.coords, c.contacts) or NOT_CLOSE_PACKED


def cluster_values(c: CoreCluster, rig: Rigidity) -> dict:
    """Column values of a new cluster row: every fact of it (all but id, embedding, the run that found
    it and how).  The write-back computes them before it takes the write lock, for the endpoints that
    match no stored cluster then (:func:`premade`); see :func:`backfill` for rows stored by an
    older version."""
    gap = c.min_gap()
    return {
        "n": c.n,
        "contacts": c.m,
        "certificate": certificate_key(c),
        "coords": np.ascontiguousarray(c.coords, dtype="<f8").tobytes(),
        "contact_list": contacts_json(c.contacts),
        "rigid_kind": rig.kind,
        "rigid_method": rig.method,
        "margin": rig.margin,
        "flexes": rig.flexes,
        "stresses": rig.stresses,
        "singular": rig.singular,
        "min_gap": gap if np.isfinite(gap) else None,
        "lattice": lattice_value(c),
        **free_energy_values(c),
    }


def free_energy_values(c: CoreCluster) -> dict:
    """The columns of the sticky-limit partition function (:func:`packings.workers.free_energy.free_energy`):
    log z, or NULL and the kind that is why; the symmetry number; the square well's leading term."""
    fe = free_energy(c)
    return {
        "sigma": fe.sigma,
        "chiral": fe.chiral,
        "log_z": fe.log_z,
        "z_reason": None if fe.log_z is not None else fe.kind,
        "eps_power": fe.eps_power,
        "log_z_square_well": None if fe.square_well is None else math.log(fe.square_well),
    }


def lock_certificates(session: Session | Connection, keys) -> None:
    """Serialise the writers of each (n, certificate) in ``keys`` to the end of the transaction
    (:func:`packings.service.db.transaction_locks`)."""
    transaction_locks(session, [("cluster", n, cert) for n, cert in keys])


@dataclass(frozen=True)
class Stored:
    """What the write-back needs of a stored cluster: its id, its embedding number, its core cluster and
    the run that found it (which gave it its expansion in that run in the same transaction)."""

    id: int
    embedding: int
    cluster: CoreCluster
    found_in_run: int | None = None


def stored_with(session: Session | Connection, n: int, certificates) -> dict[str, list[Stored]]:
    """The stored clusters of n with these certificates, by certificate, in embedding order (one query,
    of the columns the comparison needs only: the write-back runs it for every expansion)."""
    out: dict[str, list[Stored]] = {cert: [] for cert in certificates}
    if out:
        for id_, cert, embedding, coords, contact_list, run in session.execute(_STORED, {"n": n, "certs": sorted(out)}):
            out[cert].append(Stored(id_, embedding, core_cluster(n, coords, contact_list), run))
    return out


def stored_by_key(session: Session | Connection, keys) -> dict[tuple[int, str], list[Stored]]:
    """:func:`stored_with` for (n, certificate) ``keys`` of any n: one query per n."""
    by_n: dict[int, set[str]] = {}
    for n, cert in keys:
        by_n.setdefault(n, set()).add(cert)
    return {
        (n, cert): rows for n, certs in sorted(by_n.items()) for cert, rows in stored_with(session, n, certs).items()
    }


def insert_or_match(
    session: Session | Connection,
    c: CoreCluster,
    rig: Rigidity,
    run_id: int | None,
    tol_d: float,
    rows: list[Stored] | None = None,
    *,
    found_by: str,
    source_id: int | None,
    values: dict | None = None,
) -> tuple[int, bool]:
    """The id of the stored cluster equal to ``c`` (same certificate, same
    geometry within ``tol_d``), inserting it if there is none.  The caller
    holds the certificate's lock (:func:`lock_certificates`).  ``rows`` are the
    stored clusters with its certificate (:func:`stored_with`; a row inserted
    here is appended to it) if the caller has them already.  The row's values
    are ``values`` (:func:`cluster_values`, computed by the caller before it
    took the lock) or, if None, computed here, only if it is inserted: most
    endpoints are clusters stored already.  ``found_by`` and ``source_id``
    (models.FOUND_*: how it was found, and from which cluster) are written only
    if it is inserted: a cluster keeps how it was first found."""
    if rows is None:
        cert = certificate_key(c)
        rows = stored_with(session, c.n, [cert])[cert]
    if rows:
        k = find_match(c, [r.cluster for r in rows], tol_d)
        if k is not None:
            return rows[k].id, False
    # Embedding numbers follow geometry, not discovery (identity.embedding_position): the geometries
    # after the new one move up by one, the last first so that no two rows ever share a key.
    embedding = embedding_position(c, [r.cluster for r in rows], tol_d)
    moved = [replace(r, embedding=r.embedding + 1) for r in rows[embedding:]]
    for r in reversed(moved):
        session.execute(_RENUMBER, {"cid": r.id, "new_embedding": r.embedding})
    if values is None:
        values = cluster_values(c, rig)
    result = session.execute(
        _INSERT_CLUSTER,
        {**values, "embedding": embedding, "found_in_run": run_id, "found_by": found_by, "source_id": source_id},
    )
    cid = int(result.inserted_primary_key[0])
    remember_core_cluster(c.n, values["coords"], values["contact_list"], c)  # read back as c, labelled already
    rows[embedding:] = [Stored(cid, embedding, c, run_id), *moved]
    return cid, True


def ensure_expansions(session: Session | Connection, run_id: int, cluster_ids, new=()) -> int:
    """Add a pending expansion to the run for each of ``cluster_ids`` that has none, and for each of
    ``new`` (clusters inserted in this transaction, which have none yet); returns how many."""
    new = set(new)
    wanted = set(cluster_ids) - new
    have = set(session.execute(_HAVE_EXPANSIONS, {"run": run_id, "ids": sorted(wanted)}).scalars()) if wanted else set()
    missing = sorted((wanted - have) | new)
    if missing:
        session.execute(_INSERT_EXPANSION, [{"run_id": run_id, "cluster_id": c, "status": PENDING} for c in missing])
    return len(missing)


# --------------------------------------------------------------------------- runs


@dataclass(frozen=True)
class RunInfo:
    id: int
    n: int
    params: Params
    created: bool
    recovered: int = 0  #: expansions leased by a coordinator that was gone, put back to pending
    seconds: float = 0.0  #: the run's time before this coordinator took it (its earlier coordinators')


def start_run(Session_: sessionmaker, n: int, params: Params, owner: str) -> RunInfo:
    """Create the run for (n, params), or resume it; then take it over.

    A new run is seeded with one rigid cluster (packings.workers.seeds).  Resuming puts
    back to pending every expansion leased by a coordinator that is gone, without using up an
    attempt (:attr:`RunInfo.recovered` says how many).
    Raises :class:`packings.service.owners.RunBusy` if a live coordinator holds the run.
    """
    pj = params.to_json()
    with Session_.begin() as s:
        run = s.execute(select(Run).where(Run.n == n, Run.params == pj).with_for_update()).scalar_one_or_none()
        created = run is None
        if created:
            run = Run(n=n, params=pj, status=RUNNING, code_version=code_version())
            s.add(run)
            s.flush()
            seed = seed_cluster(n, params)
            rig = rigidity(seed.coords, seed.contacts, params)
            lock_certificates(s, [(n, certificate_key(seed))])
            cid, _ = insert_or_match(s, seed, rig, run.id, params.tol_d, found_by=FOUND_SEED, source_id=None)
            ensure_expansions(s, run.id, [cid])
        elif (held := busy(run.id, n, run.coordinator, run.heartbeat_at, owner)) is not None:
            raise held
        recovered = _unlease(s, run.id, retry=True)
        run.coordinator = owner
        run.heartbeat_at = utcnow()
        if run.status != COMPLETE:
            run.status = RUNNING
        run_id, seconds = run.id, run.seconds or 0.0
    return RunInfo(run_id, n, params, created, recovered, seconds)


def heartbeat(Session_: sessionmaker, run_id: int, owner: str, seconds: float | None = None) -> None:
    """Mark the run as held by ``owner`` now and, if given, record its ``seconds`` so far (the time of
    all its coordinators: :attr:`RunInfo.seconds` plus this one's), so that ``status`` shows a running
    run's time and a coordinator that is killed loses at most one beat of it."""
    values = {"heartbeat_at": utcnow(), **({} if seconds is None else {"seconds": seconds})}
    with Session_.begin() as s:
        s.execute(update(Run).where(Run.id == run_id, Run.coordinator == owner).values(**values))


def finish_run(Session_: sessionmaker, run_id: int, owner: str, seconds: float) -> str:
    """Mark the run complete (or incomplete, if some expansions failed) and let it go, its time so far
    being ``seconds`` (see :func:`heartbeat`)."""
    with Session_.begin() as s:
        run = s.get(Run, run_id)
        counts = frontier(s, run_id)
        if counts.get(PENDING, 0) == 0 and counts.get(LEASED, 0) == 0:
            run.status = INCOMPLETE if counts.get(FAILED, 0) else COMPLETE
            if not (run.finished_at and run.status == COMPLETE):  # a resumed complete run keeps its time
                run.finished_at = utcnow()
        _let_go(run, owner, seconds)
        return run.status


def abandon(Session_: sessionmaker, run_id: int, owner: str, seconds: float) -> None:
    """An interrupted coordinator puts its leases back (their attempts not used up) and lets the run go."""
    with Session_.begin() as s:
        _unlease(s, run_id, ExpansionRow.lease_owner == owner)
        _let_go(s.get(Run, run_id), owner, seconds)


def _back_to_pending(retry: bool) -> dict:
    """The values that put a leased expansion back to pending, the attempt its lease took given back
    (its coordinator or its worker, not it, stopped); with ``retry``, counted as an infrastructure
    retry (``expansions.retries``)."""
    return dict(
        status=PENDING,
        lease_owner=None,
        lease_token=None,
        leased_at=None,
        attempts=case((ExpansionRow.attempts > 0, ExpansionRow.attempts - 1), else_=0),
        retries=ExpansionRow.retries + int(retry),
    )


def _unlease(s: Session, run_id: int, *where, retry: bool = False) -> int:
    """Put the run's leased expansions (those matching ``where``) back to pending
    (:func:`_back_to_pending`; ``retry``: the coordinator was lost).  Returns how many."""
    return s.execute(
        update(ExpansionRow)
        .where(ExpansionRow.run_id == run_id, ExpansionRow.status == LEASED, *where)
        .values(**_back_to_pending(retry))
    ).rowcount


def _let_go(run: Run, owner: str, seconds: float) -> None:
    """If this coordinator holds the run: record its ``seconds`` so far (see :func:`heartbeat`) and
    release it."""
    if run.coordinator == owner:
        run.seconds = seconds
        run.coordinator = None


# --------------------------------------------------------------------------- frontier


def claimable(run_id: int, k: int):
    """The query of the run's ``k`` pending expansions a claim takes, lowest id first, skipping those
    another transaction holds: read from ``ix_expansions_pending`` (revision 0012), so that it reads
    ``k`` entries however many expansions are done or pending.  The status is written into the statement,
    not bound: a plan PostgreSQL makes for any value of a bound one could not use the partial index."""
    return (
        select(ExpansionRow)
        .where(ExpansionRow.run_id == run_id, ExpansionRow.status == literal_column(f"'{PENDING}'"))
        .order_by(ExpansionRow.id)
        .limit(k)
        .with_for_update(skip_locked=True)
    )


def claim(Session_: sessionmaker, run_id: int, owner: str, k: int) -> list[tuple[int, str]]:
    """Lease up to ``k`` pending expansions of the run; returns (id, token) pairs."""
    if k <= 0:
        return []
    with Session_.begin() as s:
        rows = s.execute(claimable(run_id, k)).scalars().all()
        out = []
        now = utcnow()
        for e in rows:
            e.status = LEASED
            e.lease_owner = owner
            e.lease_token = uuid.uuid4().hex
            e.leased_at = now
            e.attempts += 1
            out.append((e.id, e.lease_token))
        return out


def release(
    Session_: sessionmaker, expansion_id: int, token: str, error: str, max_attempts: int, isolated: bool = False
) -> str | None:
    """A task failed, and this counts against the expansion: back to pending, or ``failed`` after
    ``max_attempts``.  ``isolated``: its task ran it alone, after an infrastructure fault, and was
    lost again (counted in ``isolated_failures`` too).

    Returns the new status, or None if the lease was no longer this token's.
    """
    with Session_.begin() as s:
        e = s.execute(select(ExpansionRow).where(ExpansionRow.id == expansion_id).with_for_update()).scalar_one()
        if e.status != LEASED or e.lease_token != token:
            return None
        e.isolated_failures += int(isolated)
        e.error = error[-16000:]  # a traceback's end says most
        e.lease_owner = e.lease_token = e.leased_at = None
        e.status = FAILED if e.attempts >= max_attempts else PENDING
        if e.status == FAILED:
            e.finished_at = utcnow()
        return e.status


def put_back(Session_: sessionmaker, leases: list[tuple[int, str]], error: str, retry: bool = True) -> int:
    """A task was lost to an infrastructure fault (its worker died, the connection closed, the
    scheduler forgot it): its expansions still leased with these tokens go back to pending with
    their attempt given back, counted in ``retries`` (unless ``retry`` is False: counted already, by
    :func:`count_retries`); ``error`` is kept as the last error seen.  Returns how many."""
    if not leases:
        return 0
    with Session_.begin() as s:
        return sum(
            s.execute(
                update(ExpansionRow)
                .where(ExpansionRow.id == eid, ExpansionRow.status == LEASED, ExpansionRow.lease_token == token)
                .values(**_back_to_pending(retry=retry), error=error[-16000:])
            ).rowcount
            for eid, token in leases
        )


def count_retries(Session_: sessionmaker, expansion_ids: list[int]) -> int:
    """The task of these expansions was lost with its worker and Dask runs it again on another one
    (the coordinator learns it from the scheduler, :class:`packings.service.coordinator._Departures`):
    one more ``retries`` each, whatever their state now (the run again may have finished already).
    Returns how many."""
    if not expansion_ids:
        return 0
    with Session_.begin() as s:
        return s.execute(
            update(ExpansionRow)
            .where(ExpansionRow.id.in_(sorted(set(expansion_ids))))
            .values(retries=ExpansionRow.retries + 1)
        ).rowcount


# --------------------------------------------------------------------------- tasks


@dataclass(frozen=True)
class Task:
    """What a worker needs to expand one cluster."""

    expansion_id: int
    run_id: int
    cluster_id: int
    cluster: CoreCluster
    params: Params
    #: the run's paths that arrived at the cluster and may be retraced from it, as
    #: :func:`packings.workers.expand.arrivals` takes them: (source id, broken, new contacts, steps, labels)
    arrivals: tuple[tuple, ...] = ()


def load_task(Session_: sessionmaker, expansion_id: int, token: str) -> Task | None:
    """The task's inputs, or None if the expansion is no longer leased with ``token``."""
    return load_tasks(Session_, [(expansion_id, token)]).get(expansion_id)


def load_tasks(Session_: sessionmaker, leases) -> dict[int, Task]:
    """The inputs of the expansions in ``leases`` ((id, token) pairs), in one query: those still
    leased with their token, by id (the others are left out)."""
    tokens = dict(leases)
    if not tokens:
        return {}
    with Session_() as s:
        rows = [
            row
            for row in s.execute(_TASKS, {"eids": sorted(tokens)}).all()
            if row.status == LEASED and row.lease_token == tokens[row.id]
        ]
        came = arrivals_at(s, {(row.run_id, row.cluster_id) for row in rows})
    return {
        row.id: Task(
            row.id,
            row.run_id,
            row.cluster_id,
            core_cluster(row.n, row.coords, row.contact_list),
            _params(row.params),
            tuple(came.get((row.run_id, row.cluster_id), ())),
        )
        for row in rows
    }


@functools.lru_cache(maxsize=64)
def _params(params_text: str) -> Params:
    """A run's parameters from their JSON (a worker reads the same run's again and again)."""
    return Params.from_dict(json.loads(params_text))


def distinct_endpoints(ex: CoreExpansion) -> tuple[list[tuple[CoreCluster, Rigidity, str]], dict[int, int]]:
    """The distinct rigid endpoints of an expansion (:meth:`packings.workers.expand.Expansion.distinct`, told
    apart by :func:`packings.workers.expand.expand`), each once with its certificate, and for each rigid
    endpoint's index which of them it is."""
    first = ex.distinct()
    position = {i: k for k, i in enumerate(first)}
    distinct = [
        (ex.endpoints[i].cluster, ex.endpoints[i].rigidity, certificate_key(ex.endpoints[i].cluster)) for i in first
    ]
    which = {i: position[j] for i, j in enumerate(ex.same_as) if j is not None}
    return distinct, which


@dataclass
class Premade:
    """What a write-back works out from a read before its transaction (:func:`premade`), so that the
    transaction, which holds the write lock (SQLite) or its certificates' locks (PostgreSQL), does only
    what that read cannot settle.  Keys are (expansion, distinct endpoint) or (expansion, attempt)
    positions."""

    #: :func:`cluster_values` of each distinct endpoint that matched no stored cluster
    values: dict[tuple[int, int], dict] = field(default_factory=dict)
    #: the id of the stored cluster each other distinct endpoint matched
    matched: dict[tuple[int, int], int] = field(default_factory=dict)
    #: the ids of the stored clusters of each (n, certificate) read
    seen: dict[tuple[int, str], frozenset] = field(default_factory=dict)
    #: by expansion: the labels of its retraceable attempts whose endpoint matched, by attempt, with that
    #: cluster's id
    labels: dict[int, dict[int, tuple[int, tuple[int, ...]]]] = field(default_factory=dict)


def premade(engine, expansions: list[tuple[float, CoreExpansion, list, dict]]) -> Premade:
    """:class:`Premade` of a task's expansions (each: ``tol_d``, the expansion, and
    :func:`distinct_endpoints`' two values), from one read of the stored clusters of their
    certificates.  The transaction reads them again under its locks: where a certificate's clusters
    are still those read (the same ids: rows are never deleted, their geometry never changes, and their
    order changes only with an insert), an endpoint's match and its attempts' labels are these; else it
    matches again, and a value or label that lacks is computed there."""
    keys = {(c.n, cert) for _, _, distinct, _ in expansions for c, _, cert in distinct}
    stored: dict[tuple[int, str], list[Stored]] = {}
    if keys:
        with engine.connect().execution_options(**{READONLY: True}) as conn, conn.begin():
            stored = stored_by_key(conn, keys)
    out = Premade(seen={key: frozenset(r.id for r in rows) for key, rows in stored.items()})
    by_id = {r.id: r.cluster for rows in stored.values() for r in rows}
    for k, (tol_d, ex, distinct, which) in enumerate(expansions):
        for j, (c, rig, cert) in enumerate(distinct):
            rows = stored[(c.n, cert)]
            m = find_match(c, [r.cluster for r in rows], tol_d) if rows else None
            if m is None:
                out.values[(k, j)] = cluster_values(c, rig)
            else:
                out.matched[(k, j)] = rows[m].id
        for i, e in enumerate(ex.endpoints):
            cid = out.matched.get((k, which[i])) if i in which else None
            if cid is not None and e.reached is None and ex.retraceable(i):
                t = alignment(e.cluster, by_id[cid], tol_d, same=True)
                if t is not None:
                    out.labels.setdefault(k, {})[i] = (cid, tuple(int(x) for x in t))
    return out


@dataclass(frozen=True)
class Finished:
    """An expansion computed by a task, to be written back: the task, its lease token, the result and
    the seconds :func:`packings.workers.expand.expand` took."""

    task: Task
    token: str
    expansion: CoreExpansion
    seconds: float


def record_expansion(
    Session_: sessionmaker, task: Task, token: str, ex: CoreExpansion, seconds: float, worker: str
) -> dict | None:
    """:func:`record_expansions` of one expansion: its summary, or None (nothing written) if the lease
    is no longer ``token``'s."""
    return record_expansions(Session_, [Finished(task, token, ex, seconds)], worker)[0]


def record_expansions(Session_: sessionmaker, finished: list[Finished], worker: str) -> list[dict | None]:
    """Write a task's finished expansions back in ONE transaction (see the module doc).

    Each expansion is written only if it is still leased with its token (a task run twice, or whose
    lease was given to another, writes nothing for it); its summary is then None.  The others are
    written together: all of them or, if anything fails, none.  One transaction for a task's few
    expansions rather than one each: a write-back's fixed costs (BEGIN and COMMIT, on SQLite the one
    write lock, the query of the stored clusters, the inserts of attempts and expansions) are paid
    once per task.
    """
    prepared = [(f, *distinct_endpoints(f.expansion), _outcomes_json(f.expansion)) for f in finished]
    engine = Session_.kw["bind"]
    pre = premade(engine, [(f.task.params.tol_d, f.expansion, distinct, which) for f, distinct, which, _ in prepared])
    summaries: list[dict | None] = [None] * len(finished)
    # Core statements only, on a connection of the sessions' engine: cheaper than a session, and the
    # same transaction rules (SQLite: BEGIN IMMEDIATE).
    with engine.begin() as s:
        live = _mark_done(s, prepared, worker)
        if not live:
            return summaries
        keys = {(f.task.cluster.n, cert) for _, f, distinct, _ in live for _, _, cert in distinct}
        lock_certificates(s, keys)
        stored = stored_by_key(s, keys)
        by_id = {r.id: r.cluster for rows in stored.values() for r in rows}  # and those inserted below
        inserted: dict[int, list[int]] = {}  # by run: clusters inserted now, which get their expansion directly
        others: dict[int, list[int]] = {}  # by run: clusters found by another run, which may have none in this one
        written = []
        for k, f, distinct, which in live:
            task, ex = f.task, f.expansion
            ids, new_clusters = [], 0
            for j, (c, rig, cert) in enumerate(distinct):
                rows = stored[(c.n, cert)]
                cid, is_new = _store_endpoint(s, task, c, rig, cert, rows, pre, (k, j))
                ids.append(cid)
                if is_new:
                    by_id[cid] = c  # the stored row's core cluster (insert_or_match)
                    inserted.setdefault(task.run_id, []).append(cid)
                    new_clusters += 1
                elif next(r.found_in_run for r in rows if r.id == cid) != task.run_id:
                    others.setdefault(task.run_id, []).append(cid)
            targets = _targets(ex, task.cluster_id, ids, which)
            known = {i: lab for i, (cid, lab) in pre.labels.get(k, {}).items() if targets.get(i) == cid}
            labels = _target_labels(ex, targets, by_id, task.params.tol_d, known)
            written.append((task.run_id, task.cluster_id, task.cluster.n, _attempts(ex, targets, labels)))
            summaries[k] = {
                "expansion": task.expansion_id,
                "new_clusters": new_clusters,
                "paths": ex.paths_followed,
                "seconds": f.seconds,
            }
        for run_id in sorted(inserted.keys() | others.keys()):
            ensure_expansions(s, run_id, others.get(run_id, ()), new=inserted.get(run_id, ()))
        insert_attempts(s, written)
    return summaries


def _outcomes_json(ex: CoreExpansion) -> str:
    """expansions.outcomes of an expansion: its attempts by outcome, and its widened, symmetric and
    retraced paths; a count of none is left out, as an outcome no attempt had is (readers take it as 0)."""
    outcomes = dict(sorted(ex.outcomes().items()))
    outcomes["widened_paths"] = ex.widened_paths
    outcomes["paths_by_symmetry"] = ex.paths_by_symmetry
    outcomes["paths_retraced"] = ex.paths_retraced
    return json.dumps({k: v for k, v in outcomes.items() if v})


def _mark_done(s: Connection, prepared: list[tuple], worker: str) -> list[tuple]:
    """The write-back's first statements: each expansion of ``prepared`` (finished, distinct endpoints, which,
    outcomes) done, if its lease is still its token's (PostgreSQL: this also locks the row).  Nothing of it
    is seen by others before the commit, and all of it is rolled back if anything after fails.  Returns
    (position, finished, distinct, which) of those marked."""
    live = []
    for k, (f, distinct, which, outcomes) in enumerate(prepared):
        done = s.execute(
            _DONE,
            {
                "eid": f.task.expansion_id,
                "token": f.token,
                "status": DONE,
                "finished_at": utcnow(),
                "lease_owner": None,
                "lease_token": None,
                "outcomes": outcomes,
                "paths": f.expansion.paths_followed,
                "seconds": f.seconds,
                "worker": worker,
                "error": None,
            },
        )
        if done.rowcount == 1:
            live.append((k, f, distinct, which))
    return live


def _store_endpoint(
    s: Connection,
    task: Task,
    c: CoreCluster,
    rig: Rigidity,
    cert: str,
    rows: list[Stored],
    pre: Premade,
    at: tuple[int, int],
) -> tuple[int, bool]:
    """The id of the stored cluster a distinct endpoint ``c`` of ``task`` (certificate ``cert``, position
    ``at`` in :class:`Premade`) is, and whether it was inserted now: the match read before if the
    certificate's clusters (``rows``, read under its lock) are still those, else :func:`insert_or_match`."""
    cid = pre.matched.get(at)
    if cid is not None and pre.seen[(c.n, cert)] == frozenset(r.id for r in rows):
        return cid, False  # the clusters read before: the same match
    return insert_or_match(
        s,
        c,
        rig,
        task.run_id,
        task.params.tol_d,
        rows,
        found_by=FOUND_PATH,
        source_id=task.cluster_id,
        values=pre.values.get(at),
    )


def _targets(ex: CoreExpansion, source_id: int, ids, which: dict[int, int]) -> dict[int, int]:
    """The cluster each attempt of ``ex`` reached, by attempt: its rigid endpoint's stored cluster (``ids``,
    by distinct endpoint), the source itself for a circular or rearranged one, a retraced path's target."""
    targets = {i: ids[j] for i, j in which.items()}
    targets.update({i: source_id for i, e in enumerate(ex.endpoints) if e.outcome in (CIRCULAR, REARRANGED)})
    targets.update({i: e.reached.target for i, e in enumerate(ex.endpoints) if e.reached is not None})
    return targets


def _target_labels(
    ex: CoreExpansion, targets: dict[int, int], by_id: dict[int, CoreCluster], tol_d: float, known=None
) -> dict[int, tuple[int, ...]]:
    """The labels (:attr:`packings.service.paths_codec.Attempt.labels`) of the attempts of ``ex`` that a path
    of their target may retrace (:meth:`packings.workers.expand.Expansion.retraceable`): each endpoint
    relabelled onto its target as stored (``by_id``: the core clusters of the rows the write-back matched
    or inserted); and of the attempts taken from such a path (:attr:`packings.workers.expand.Endpoint.reached`).
    ``known``: those of some attempts already (:attr:`Premade.labels`, made against the same target)."""
    out = dict(known or {})
    for i, e in enumerate(ex.endpoints):
        if i in out:
            continue
        if e.reached is not None:
            out[i] = tuple(int(k) for k in e.reached.labels)
        elif ex.retraceable(i):
            t = alignment(e.cluster, by_id[targets[i]], tol_d, same=True)
            if t is not None:  # it matched the row: only a tolerance's rounding could make it None
                out[i] = tuple(int(k) for k in t)
    return out


def _attempts(ex: CoreExpansion, targets: dict[int, int], labels: dict[int, tuple[int, ...]]) -> list[Attempt]:
    """The attempts of ``ex``, each with the cluster it reached (``targets``) and its labels (the endpoints'
    own pairs, shared, not copied: an expansion may have hundreds of thousands of attempts)."""
    return [
        Attempt(e.broken, e.direction, e.outcome, targets.get(i), e.steps, e.new_contacts, labels.get(i))
        for i, e in enumerate(ex.endpoints)
    ]


def attempts_rows(run_id: int, source_id: int, n: int, attempts: list[Attempt]) -> tuple[tuple, list[tuple]]:
    """The ``attempts`` row (:data:`ATTEMPTS_COLUMNS`' values) of one expansion's attempts and its
    ``edges`` rows (:data:`EDGE_COLUMNS`')."""
    sm = summary(attempts)
    row = (run_id, source_id, sm.attempts, sm.paths, sm.circular, sm.rearranged, pack(n, attempts))
    return row, [(t, source_id, run_id, p, lab) for t, (p, lab) in sorted(sm.edges.items())]


def insert_attempts(conn: Connection, expansions: Iterable[tuple[int, int, int, list[Attempt]]]) -> None:
    """Insert the attempts of expansions, each given as (run id, source id, n, attempts): one ``attempts``
    row each, and its ``edges`` (:func:`packings.service.db.insert_many`)."""
    rows, edges = [], []
    for run_id, source_id, n, attempts in expansions:
        row, e = attempts_rows(run_id, source_id, n, attempts)
        rows.append(row)
        edges += e
    insert_many(conn, _A, ATTEMPTS_COLUMNS, rows)
    insert_many(conn, _EDGES, EDGE_COLUMNS, edges)


#: rows stored by an older version: without the lattice (before revision 0002) or the free energy (0010)
_MISSING_FACTS = ClusterRow.lattice.is_(None) | ClusterRow.sigma.is_(None)


def backfill(Session_: sessionmaker, recompute: bool = False, batch: int = 500, on_batch=None) -> int:
    """Compute the facts that rows stored by an older version lack (the
    lattice, min_gap, and the free energy's columns from the coordinates);
    with ``recompute``, every row's.  One transaction per batch, so an interruption loses nothing: a
    row is either done or still NULL.  Returns the number of rows updated."""
    done = 0
    last_id = 0
    while True:
        with Session_.begin() as s:
            q = select(ClusterRow).where(ClusterRow.id > last_id).order_by(ClusterRow.id).limit(batch)
            if not recompute:
                q = q.where(_MISSING_FACTS)
            rows = s.execute(q).scalars().all()
            if not rows:
                return done
            for row in rows:
                c = row.to_core()
                gap = c.min_gap()
                row.min_gap = gap if np.isfinite(gap) else None
                row.lattice = lattice_value(c)
                for name, value in free_energy_values(c).items():
                    setattr(row, name, value)
            last_id = rows[-1].id
            done += len(rows)
        if on_batch is not None:
            on_batch(done)


def to_backfill(s: Session, recompute: bool = False) -> int:
    """Rows that :func:`backfill` would update: those whose facts are missing, or all."""
    q = select(func.count()).select_from(ClusterRow)
    return s.execute(q if recompute else q.where(_MISSING_FACTS)).scalar_one()


# --------------------------------------------------------------------------- a run's results
