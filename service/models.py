"""The database schema (SQLAlchemy 2 declarative models).

The schema changes only through Alembic migrations (``alembic/versions``); a
test checks that the migrations' head matches these models.  The README
documents the tables for users who query them with plain SQL or pandas.

Conventions:

* Coordinates are stored once, as the raw little-endian float64 bytes of the
  n x 3 array (``coords``), so they read back bit-exactly (``packings export``
  and the Python API give them as numbers).
* Contact lists are stored as bytes, two a contact (``i``, ``j`` as unsigned bytes, ``i < j``, sorted:
  ``clusters.contact_pairs``, revision 0011) and given to Python as the JSON text ``[[i, j], ...]``
  (:class:`ContactPairs`).
* The attempts of an expansion are one row of ``attempts``, packed
  (:mod:`packings.service.paths_codec`); ``edges`` holds the clusters each
  expansion reached, so that paths are counted and followed back in SQL.
* Clusters are keyed by ``(n, certificate, embedding)``; ``certificate`` is the
  portable hex key of :func:`packings.workers.identity.certificate_key`, and
  ``embedding`` numbers the distinct geometries sharing one contact graph, by
  shape (:func:`packings.workers.identity.embedding_position`), so that a key
  names the same geometry in every run.
"""

from __future__ import annotations

import datetime as dt
import functools
import json
import threading

import numpy as np
from sqlalchemy import (
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
    text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, query_expression

from packings.service.owners import utcnow
from packings.workers.cluster import Cluster as CoreCluster

# Expansion statuses.
PENDING = "pending"
LEASED = "leased"
DONE = "done"
FAILED = "failed"

# How a cluster was first found (clusters.found_by).
FOUND_SEED = "seed"  #: a run's starting cluster (packings.workers.seeds)
FOUND_PATH = "path"  #: the endpoint of a path from clusters.source_id
FOUND_CATALYSIS = "catalysis"  #: a remainder of clusters.source_id (more spheres) after deleting spheres
FOUND_CLOSE_PACKED = "close-packed"  #: a close-packed fragment (packings.workers.fragments), no source

# How a catalysis pass made its parents' remainders (catalysis_passes.kind).
PASS_GLUED = "glued"  #: one sphere of each stored cluster of n moved onto each contact triangle
PASS_DELETED = "deleted"  #: spheres deleted from each stored cluster of n + spheres

# Run statuses.
RUNNING = "running"
COMPLETE = "complete"
INCOMPLETE = "incomplete"  #: finished with failed expansions

#: clusters.lattice of a cluster that is not a close-packed fragment (NULL means not yet classified)
NOT_CLOSE_PACKED = "none"


class Base(DeclarativeBase):
    pass


class Run(Base):
    """One enumeration: n and the parameters it used.  ``packings enumerate``
    resumes the run with the same n and parameters if there is one."""

    __tablename__ = "runs"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    n: Mapped[int] = mapped_column(Integer, index=True)
    params: Mapped[str] = mapped_column(Text)  #: JSON of packings.workers.params.Params
    status: Mapped[str] = mapped_column(String(16), default=RUNNING)
    started_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    code_version: Mapped[str] = mapped_column(String(64))
    coordinator: Mapped[str | None] = mapped_column(
        String(200), nullable=True
    )  #: host:pid:token of the live coordinator
    heartbeat_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    seconds: Mapped[float] = mapped_column(Float, default=0.0)  #: wall time spent by coordinators on this run

    __table_args__ = (UniqueConstraint("n", "params", name="uq_runs_n_params"),)


def pack_pairs(pairs) -> bytes:
    """The contact pairs ``[[i, j], ...]`` (sphere numbers 0..255) as bytes, two a pair."""
    return bytes(int(k) for pair in pairs for k in pair)


def format_pairs(pairs) -> str:
    """The JSON text ``[[i, j], ...]`` of the pairs, exactly as ``json.dumps`` writes it."""
    return "[" + ", ".join(f"[{int(i)}, {int(j)}]" for i, j in pairs) + "]"


@functools.lru_cache(maxsize=65536)
def pairs_json(packed: bytes) -> str:
    """The JSON text ``[[i, j], ...]`` of packed pairs (:func:`format_pairs`)."""
    return format_pairs(zip(packed[0::2], packed[1::2]))


class ContactPairs(TypeDecorator):
    """A cluster's contact list, stored as bytes (:func:`pack_pairs`: about a quarter of its JSON text)
    and given to Python as the JSON text ``[[i, j], ...]`` that the service compares and keeps
    (:func:`packings.service.store.contacts_json`); it takes that text, or the pairs themselves."""

    impl = LargeBinary
    cache_ok = True

    def process_bind_param(self, value, dialect):
        if value is None:
            return None
        return pack_pairs(json.loads(value) if isinstance(value, str) else value)

    def process_result_value(self, value, dialect):
        return None if value is None else pairs_json(bytes(value))


class ClusterRow(Base):
    """A distinct rigid cluster, shared by every run with the same n."""

    __tablename__ = "clusters"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    n: Mapped[int] = mapped_column(Integer)
    contacts: Mapped[int] = mapped_column(Integer)  #: number of contacts m
    certificate: Mapped[str] = mapped_column(String(200))  #: packings.workers.identity.certificate_key
    embedding: Mapped[int] = mapped_column(Integer)  #: 0, 1, ... among clusters with this certificate, by shape
    coords: Mapped[bytes] = mapped_column(LargeBinary)  #: n x 3 float64, little-endian
    #: the contacts: column ``contact_pairs`` (two bytes a contact), read and written as JSON ``[[i, j], ...]``
    contact_list: Mapped[str] = mapped_column("contact_pairs", ContactPairs, key="contact_list")
    rigid_kind: Mapped[str] = mapped_column(String(32))  #: packings.workers.rigidity kind (first-order / prestress)
    rigid_method: Mapped[str] = mapped_column(String(32))  #: which test decided
    margin: Mapped[float | None] = mapped_column(Float, nullable=True)
    flexes: Mapped[int] = mapped_column(Integer)
    stresses: Mapped[int] = mapped_column(Integer)
    singular: Mapped[bool] = mapped_column(Boolean)
    min_gap: Mapped[float | None] = mapped_column(Float, nullable=True)  #: None if every pair touches
    #: packings.workers.classify.lattice_type: fcc, hcp, both, random, 2d, or 'none' (not close-packed);
    #: NULL only for rows stored before revision 0002 until the backfill (``packings db upgrade``) ran
    lattice: Mapped[str | None] = mapped_column(String(16), nullable=True)
    found_in_run: Mapped[int | None] = mapped_column(ForeignKey("runs.id"), nullable=True)
    #: FOUND_SEED, FOUND_PATH, FOUND_CATALYSIS or FOUND_CLOSE_PACKED: how the cluster was first found (revision 0003)
    found_by: Mapped[str] = mapped_column(String(16), server_default=FOUND_PATH)
    #: the cluster it was found from: for a path, the cluster whose expansion reached it; for catalysis,
    #: the cluster of more spheres it is a remainder of; None for a seed and a close-packed fragment
    source_id: Mapped[int | None] = mapped_column(
        ForeignKey("clusters.id", name="fk_clusters_source_id"), nullable=True
    )
    #: the sticky-limit partition function Z = κ^m z (packings.workers.free_energy, revision 0010); sigma is
    #: NULL only for rows stored before 0010 until the backfill ran
    sigma: Mapped[int | None] = mapped_column(Integer, nullable=True)  #: symmetry number (proper rotations)
    chiral: Mapped[bool | None] = mapped_column(Boolean, nullable=True)  #: its mirror image is not a rotation of it
    log_z: Mapped[float | None] = mapped_column(Float, nullable=True)  #: log z; NULL where Z is not κ^m z
    #: why log_z is NULL: singular, hypostatic or hyperstatic (packings.workers.free_energy.REASONS)
    z_reason: Mapped[str | None] = mapped_column(String(16), nullable=True)
    #: a square well of width ε: Z = κ^m ε^eps_power exp(log_z_square_well) to leading order, where computed
    eps_power: Mapped[float | None] = mapped_column(Float, nullable=True)
    log_z_square_well: Mapped[float | None] = mapped_column(Float, nullable=True)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    #: not a column: the number of stored clusters sharing this one's contact graph, filled in by
    #: packings.service.selection.query (None when the row was loaded another way)
    geometries: Mapped[int | None] = query_expression()

    __table_args__ = (
        UniqueConstraint("n", "certificate", "embedding", name="uq_clusters_key"),
        Index("ix_clusters_n_contacts", "n", "contacts"),
        Index("ix_clusters_n_lattice", "n", "lattice"),
        Index("ix_clusters_source", "source_id"),
    )

    def to_core(self) -> CoreCluster:
        return core_cluster(self.n, self.coords, self.contact_list)


CORE_CLUSTERS = 32768  #: how many core clusters :func:`core_cluster` keeps (the most recently used)
_CORE: dict[tuple[int, bytes, str], CoreCluster] = {}  #: in order of use, the most recent last
_CORE_LOCK = threading.Lock()


def core_cluster(n: int, coords: bytes, contact_list: str) -> CoreCluster:
    """The (immutable) core cluster of a row's values, shared by every row with the same values, so
    that what is computed from it once (its canonical form, packings.workers.identity) is kept: a worker
    compares each new endpoint with the same stored rows again and again.  Keyed by the values, not
    the id, which SQLite may give again after a rollback."""
    key = (n, coords, contact_list)
    with _CORE_LOCK:
        c = _CORE.pop(key, None)
        if c is not None:
            _CORE[key] = c
            return c
    x = np.frombuffer(coords, dtype="<f8").reshape(n, 3).astype(np.float64)
    c = CoreCluster(x, tuple(tuple(p) for p in json.loads(contact_list)))
    remember_core_cluster(n, coords, contact_list, c)
    return c


def remember_core_cluster(n: int, coords: bytes, contact_list: str, c: CoreCluster) -> None:
    """Make ``c`` the core cluster of these row values (a row just written from it, with values
    computed from it: equal coordinates and contacts), so that what was computed from ``c`` already (its
    canonical form, when its expansion told its endpoints apart) is not computed again for the row."""
    key = (n, coords, contact_list)
    with _CORE_LOCK:
        _CORE.pop(key, None)
        _CORE[key] = c
        while len(_CORE) > CORE_CLUSTERS:
            del _CORE[next(iter(_CORE))]


_PENDING_ONLY = text(f"status = '{PENDING}'")  #: the rows ix_expansions_pending holds


class ExpansionRow(Base):
    """The frontier: one row per (run, cluster) to expand."""

    __tablename__ = "expansions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"))
    cluster_id: Mapped[int] = mapped_column(ForeignKey("clusters.id"))
    status: Mapped[str] = mapped_column(String(16), default=PENDING)
    #: leases that counted against max_attempts: a failure of the expansion itself, or of its task alone
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    #: times it was put back because of an infrastructure fault (a worker or a coordinator lost), uncounted
    retries: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    #: times its task, run alone after such a fault, was lost again (each one counted in attempts)
    isolated_failures: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    lease_owner: Mapped[str | None] = mapped_column(String(200), nullable=True)
    lease_token: Mapped[str | None] = mapped_column(String(64), nullable=True)
    leased_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    outcomes: Mapped[str | None] = mapped_column(Text, nullable=True)  #: JSON {outcome: count} of its attempts
    paths: Mapped[int | None] = mapped_column(Integer, nullable=True)  #: paths followed
    seconds: Mapped[float | None] = mapped_column(Float, nullable=True)  #: time spent in packings.workers.expand
    worker: Mapped[str | None] = mapped_column(String(200), nullable=True)

    __table_args__ = (
        UniqueConstraint("run_id", "cluster_id", name="uq_expansions_run_cluster"),
        Index("ix_expansions_run_status", "run_id", "status"),
        #: what a claim reads: the pending expansions of a run, lowest id first (revision 0012)
        Index("ix_expansions_pending", "run_id", "id", postgresql_where=_PENDING_ONLY, sqlite_where=_PENDING_ONLY),
    )


class CatalysisPass(Base):
    """A catalysis pass that ran to its end (:func:`packings.service.catalysis.catalyse`): which run its finds went
    to, how its parents were made, and the largest parent id it read.  ``packings enumerate N --glued``
    takes as the parents of its next pass only the clusters stored after that id."""

    __tablename__ = "catalysis_passes"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"), index=True)
    kind: Mapped[str] = mapped_column(String(16))  #: PASS_GLUED or PASS_DELETED
    spheres: Mapped[int] = mapped_column(Integer)  #: spheres deleted from each parent (1 with glued)
    after: Mapped[int] = mapped_column(Integer, default=0)  #: parents read: the clusters with a larger id
    last_parent: Mapped[int | None] = mapped_column(Integer, nullable=True)  #: the largest parent id read
    parents: Mapped[int] = mapped_column(Integer, default=0)
    remainders: Mapped[int] = mapped_column(Integer, default=0)  #: remainders decided
    rigid: Mapped[int] = mapped_column(Integer, default=0)
    new: Mapped[int] = mapped_column(Integer, default=0)  #: clusters it stored
    started_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    finished_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)


class AttemptsRow(Base):
    """Every attempt of one expansion (run, source cluster) in one row: the contacts broken, the direction
    followed, what came of each, the cluster reached (if it is stored), the steps, the contacts formed
    and the endpoint's labels as the target is stored, packed by :mod:`packings.service.paths_codec`
    (``data``).  ``attempts``, ``paths``, ``circular`` and ``rearranged`` count them, so that counting paths reads no
    packed data; :class:`Edge` says which clusters each reached."""

    __tablename__ = "attempts"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)  #: in order of writing
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"))
    source_id: Mapped[int] = mapped_column(ForeignKey("clusters.id"))
    attempts: Mapped[int] = mapped_column(Integer)  #: subsets tried, with each direction
    paths: Mapped[int] = mapped_column(Integer)  #: attempts with a direction (followed, by symmetry or retraced)
    circular: Mapped[int] = mapped_column(Integer)  #: paths that came back to the source, every sphere in place
    #: paths that ended at the source with its spheres permuted (revision 0010; 0 on rows stored before)
    rearranged: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    data: Mapped[bytes] = mapped_column(LargeBinary)  #: packings.service.paths_codec.pack

    __table_args__ = (UniqueConstraint("source_id", "run_id", name="uq_attempts_source_run"),)


class Edge(Base):
    """The clusters reached from each expansion: (target, source, run) with the number of its attempts
    that ended at the target, and how many of those carry the endpoint's labels (a path of the target
    may retrace them: docs/method.md).  Keyed by target first: the paths reaching a cluster, and the
    arrivals a task reads, are a range of the key (SQLite: WITHOUT ROWID, the key is the table)."""

    __tablename__ = "edges"

    target_id: Mapped[int] = mapped_column(ForeignKey("clusters.id"), primary_key=True)
    source_id: Mapped[int] = mapped_column(ForeignKey("clusters.id"), primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"), primary_key=True)
    paths: Mapped[int] = mapped_column(Integer)  #: attempts from source that reached target (each a path)
    labelled: Mapped[int] = mapped_column(Integer)  #: of those, the ones with the endpoint's labels

    __table_args__ = {"sqlite_with_rowid": False}
