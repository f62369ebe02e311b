"""Opening a database: URLs, engines, and the schema check.

* ``--db URL`` defaults to the ``PACKINGS_DB`` environment variable, else
  ``sqlite:///packings.db`` (a file in the working directory).  A bare file
  name (``packings.db``) is taken as SQLite; ``postgresql://`` URLs use the
  psycopg (3) driver.
* SQLite: WAL journal, a busy timeout, foreign keys on, and every
  transaction begins ``IMMEDIATE`` (it takes the write lock at once, so two
  writers never deadlock on a lock upgrade; they queue, polling the lock
  every few milliseconds up to the busy timeout), except read-only ones.
* The schema is Alembic's: a database with no tables is created at head when
  the caller may create (``packings enumerate``, ``packings db upgrade``); a
  database at another revision, or with tables that are not ours, is refused
  with one line naming the fix.  Nothing is written before that check passes.
"""

from __future__ import annotations

import hashlib
import os
import time
from importlib import resources
from itertools import islice
from pathlib import Path
from typing import Callable, Iterable

from sqlalchemy import Engine, create_engine, event, inspect, text
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError, NoSuchModuleError, OperationalError, SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from packings.service.errors import PackingsError

DEFAULT_URL = "sqlite:///packings.db"
SQLITE_BUSY_TIMEOUT_MS = 120_000
READONLY = "packings_readonly"  #: execution option: a SQLite transaction that only reads begins DEFERRED


class DatabaseError(PackingsError):
    """A problem with the database a user can fix; the message is one line."""


def default_url() -> str:
    return os.environ.get("PACKINGS_DB") or DEFAULT_URL


def absolute(u: URL) -> URL:
    """``u`` with a relative SQLite file path made absolute (a worker may run in another directory)."""
    if (
        u.get_backend_name() == "sqlite"
        and u.database
        and u.database != ":memory:"
        and not u.database.startswith("file:")
    ):
        u = u.set(database=str(Path(u.database).expanduser().resolve()))
    return u


def parse_url(url: str) -> URL:
    """The SQLAlchemy URL for ``url`` (a URL, or a bare SQLite file name)."""
    url = url.strip()
    if not url:
        raise DatabaseError("empty database URL; give e.g. sqlite:///packings.db or postgresql://user@host/db")
    if "://" not in url:
        looks_like_scheme = ":" in url or url.lower().startswith(("sqlite", "postgres"))
        if url.endswith((".db", ".sqlite", ".sqlite3")) and not looks_like_scheme:
            url = f"sqlite:///{url}"
        else:
            raise DatabaseError(
                f"malformed database URL {url!r}: expected e.g. sqlite:///packings.db or postgresql://user@host/db"
            )
    try:
        u = make_url(url)
    except (ArgumentError, ValueError) as e:
        raise DatabaseError(f"malformed database URL {url!r}: {e}") from None
    if u.drivername in ("postgresql", "postgres"):
        u = u.set(drivername="postgresql+psycopg")
    if u.get_backend_name() not in ("sqlite", "postgresql"):
        raise DatabaseError(
            f"unsupported database {u.get_backend_name()!r} in {url!r}: use sqlite:/// or postgresql://"
        )
    if u.get_backend_name() == "sqlite" and _in_memory(u):
        raise DatabaseError(
            f"{url!r} is an in-memory SQLite database, which only the process that opens it sees "
            "(the workers would not): give a file, e.g. sqlite:///packings.db"
        )
    _check_driver(u, url)
    return u


def _in_memory(u: URL) -> bool:
    db = u.database or ""
    return db in ("", ":memory:") or (
        db.startswith("file:") and ("mode=memory" in db or db.startswith("file::memory:"))
    )


def _check_driver(u: URL, url: str) -> None:
    """Refuse, in one line, a driver that is not installed or that the service cannot use (an async one).
    Supported: sqlite:/// (Python's sqlite3), postgresql:// (psycopg 3, installed with packings), and
    postgresql+psycopg2:// where psycopg2 is installed."""
    plain = {"sqlite": "sqlite:///", "postgresql": "postgresql://"}[u.get_backend_name()]
    try:
        dialect = u.get_dialect()
    except NoSuchModuleError:
        raise DatabaseError(
            f"unknown database driver {u.drivername!r} in {url!r}: use sqlite:/// or postgresql://"
        ) from None
    if getattr(dialect, "is_async", False):
        raise DatabaseError(f"{u.drivername!r} is an asyncio driver, which packings does not use: use {plain} instead")
    try:
        dialect.import_dbapi()
    except ImportError as e:
        raise DatabaseError(
            f"the driver of {u.drivername!r} is not installed ({e.name or e}): use {plain} or install it"
        ) from None


def display_url(url: URL) -> str:
    return url.render_as_string(hide_password=True)


def _sqlite_path(url: URL) -> Path | None:
    db = url.database
    if not db or db == ":memory:" or db.startswith("file:"):
        return None
    return Path(db)


def _missing_sqlite_file(engine: Engine, create: bool) -> bool:
    """Whether ``engine`` is a SQLite file that does not exist yet; an error
    unless it may be created (``create``) in a directory that exists."""
    path = _sqlite_path(engine.url) if engine.dialect.name == "sqlite" else None
    if path is None or path.exists():
        return False
    if not create:  # said alike to the command line and the Python API
        raise DatabaseError(
            f"no database at {path}: run `packings enumerate N` to make one, or give the URL of another "
            "(or set $PACKINGS_DB)"
        )
    if not path.parent.exists():
        raise DatabaseError(f"cannot create {path}: directory {path.parent} does not exist")
    if not os.access(path.parent, os.W_OK):
        raise DatabaseError(f"cannot create {path}: directory {path.parent} is not writable")
    return True


def _unwritable_directory(engine: Engine) -> Path | None:
    """The directory of ``engine``'s SQLite file, if this process cannot write in it: SQLite then cannot
    make the journal it keeps beside the file (its own error says only "unable to open database file")."""
    path = _sqlite_path(engine.url) if engine.dialect.name == "sqlite" else None
    if path is None or not path.parent.exists() or os.access(path.parent, os.W_OK):
        return None
    return path.parent


def make_engine(url: str | URL) -> Engine:
    """An engine for ``url`` with this project's connection settings (no I/O yet)."""
    u = parse_url(url) if isinstance(url, str) else url
    try:
        if u.get_backend_name() == "sqlite":
            engine = create_engine(u, connect_args={"timeout": SQLITE_BUSY_TIMEOUT_MS / 1000})
            _configure_sqlite(engine)
        else:
            engine = create_engine(u, pool_pre_ping=True, pool_size=2, max_overflow=4)
    except (ArgumentError, NoSuchModuleError, ValueError) as e:
        raise DatabaseError(f"cannot use database URL {display_url(u)!r}: {e}") from None
    return engine


def _configure_sqlite(engine: Engine) -> None:
    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection, _record):
        # Let SQLAlchemy, not pysqlite, emit BEGIN (see the "begin" hook below).
        dbapi_connection.isolation_level = None
        cur = dbapi_connection.cursor()
        cur.execute("PRAGMA journal_mode=WAL")
        cur.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
        cur.execute("PRAGMA foreign_keys=ON")
        cur.execute("PRAGMA synchronous=NORMAL")
        cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn):
        # Readers (sessions(engine, readonly=True)) take no lock: WAL gives them a snapshot.
        if conn.get_execution_options().get(READONLY):
            conn.exec_driver_sql("BEGIN")
        else:
            _begin_immediate(conn)


def _begin_immediate(conn) -> None:
    """BEGIN IMMEDIATE, waiting for the write lock by polling it every 0.2-2 ms.

    SQLite's own busy handler sleeps 1, 2, 5, 10, 15, ... ms between tries, while a
    write-back holds the lock for a few ms: with several workers writing, much of the waiting
    was its oversleeping.  So the busy timeout is off while BEGIN IMMEDIATE is tried, and set
    back at once (the transaction's other statements, and readers on this connection later,
    keep it); after SQLITE_BUSY_TIMEOUT_MS the error is SQLite's "database is locked".
    """
    raw = conn.connection.driver_connection
    raw.execute("PRAGMA busy_timeout=0")
    try:
        deadline = time.monotonic() + SQLITE_BUSY_TIMEOUT_MS / 1000
        pause = 0.0002
        while True:
            try:
                conn.exec_driver_sql("BEGIN IMMEDIATE")
                return
            except OperationalError as e:
                if "locked" not in str(e.orig) or time.monotonic() >= deadline:
                    raise
            time.sleep(pause)
            pause = min(2 * pause, 0.002)
    finally:
        raw.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")


def is_postgresql(engine_or_session) -> bool:
    bind = engine_or_session.get_bind() if isinstance(engine_or_session, Session) else engine_or_session
    return bind.dialect.name == "postgresql"


#: the advisory locks of a transaction, taken one after another in the order of the array given
_LOCKS = text("SELECT count(pg_advisory_xact_lock(k)) FROM unnest(CAST(:keys AS bigint[])) AS k")


def transaction_locks(conn, keys) -> None:
    """Serialise writers on each of ``keys`` (tuples) until the transaction ends: PostgreSQL's
    advisory transaction locks, taken in sorted order (no deadlock between two writers); nothing on
    SQLite, whose writers hold the one write lock already (every transaction that writes begins
    IMMEDIATE)."""
    if not is_postgresql(conn):
        return
    # One statement for all of them (a write-back takes one per certificate of its endpoints: dozens), the
    # locks taken in the order of the sorted array, which unnest keeps
    ints = sorted({advisory_key(*key) for key in keys})
    if ints:
        conn.execute(_LOCKS, {"keys": ints})


#: rows an insert_many statement takes at once (the rows may be made as they are inserted rather than
#: all held at once)
INSERT_CHUNK = 10_000


def insert_many(conn, table, columns: tuple[str, ...], rows: Iterable[tuple]) -> None:
    """Insert ``rows`` (tuples of ``columns``' values; any iterable, consumed ``INSERT_CHUNK`` rows at a
    time) into ``table``.  On SQLite straight through the driver's ``executemany`` (SQLAlchemy's
    processing of each row's parameters costs more than the insert); elsewhere as a Core insert (on
    PostgreSQL SQLAlchemy sends many rows in each statement)."""
    rows = iter(rows)
    while chunk := list(islice(rows, INSERT_CHUNK)):
        if conn.dialect.name == "sqlite":
            conn.exec_driver_sql(
                f"INSERT INTO {table.name} ({', '.join(columns)}) VALUES ({', '.join('?' * len(columns))})", chunk
            )
        else:
            conn.execute(table.insert(), [dict(zip(columns, r)) for r in chunk])


def advisory_key(*parts) -> int:
    """A signed 64-bit key for ``pg_advisory_xact_lock`` from any parts."""
    h = hashlib.blake2b(":".join(map(str, parts)).encode(), digest_size=8).digest()
    return int.from_bytes(h, "big", signed=True)


# --------------------------------------------------------------------------- schema


def migrations_dir() -> Path:
    """The Alembic migrations shipped inside the package (``packings/migrations``; the
    repository's ``alembic/`` folder, which ``pyproject.toml`` maps there)."""
    path = Path(str(resources.files("packings.service"))).parent / "migrations"
    if not (path / "env.py").is_file():
        raise DatabaseError(f"the package's migrations are missing ({path}); reinstall packings from its wheel")
    return path


def alembic_config(engine: Engine | None = None):
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(migrations_dir()))
    if engine is not None:
        cfg.set_main_option("sqlalchemy.url", engine.url.render_as_string(hide_password=False).replace("%", "%%"))
    return cfg


def head_revision() -> str:
    from alembic.script import ScriptDirectory

    return ScriptDirectory.from_config(alembic_config()).get_current_head()


def known_revisions() -> set[str]:
    from alembic.script import ScriptDirectory

    return {s.revision for s in ScriptDirectory.from_config(alembic_config()).walk_revisions()}


def current_revision(engine: Engine) -> str | None:
    """The database's Alembic revision (None if it has no alembic_version table)."""
    with engine.connect() as conn:
        if not inspect(conn).has_table("alembic_version"):
            return None
        return conn.execute(text("SELECT version_num FROM alembic_version")).scalar()


def upgrade(engine: Engine) -> None:
    """Bring the schema to head (Alembic's upgrade)."""
    migrate(engine, "head")


def migrate(engine: Engine, revision: str, down: bool = False) -> None:
    """Alembic's upgrade (or, ``down``, downgrade) to ``revision``, in one transaction on a connection
    of ``engine`` (handed to the migrations outside a transaction: on SQLite they switch foreign keys
    off first, see the migrations' env.py)."""
    from alembic import command

    cfg = alembic_config(engine)
    with engine.connect() as conn:
        # one migration at a time (two coordinators starting on an empty database would both create the
        # tables): the lock is held to the commit, and the second one then finds the schema at head
        transaction_locks(conn, [("schema",)])
        cfg.attributes["connection"] = conn
        (command.downgrade if down else command.upgrade)(cfg, revision)


def first_line(e: BaseException) -> str:
    """The first line of a database error's message (the driver's own, when there is one)."""
    msg = str(getattr(e, "orig", None) or e).strip().splitlines()
    return msg[0] if msg else type(e).__name__


def connect_error(engine: Engine, e: Exception) -> DatabaseError:
    where = _unwritable_directory(engine)
    if where is not None and "unable to open database file" in str(e):
        return DatabaseError(
            f"cannot open {engine.url.database}: directory {where} is not writable (SQLite keeps its journal "
            "beside the database file): make it writable, or move the database"
        )
    return DatabaseError(f"cannot connect to {display_url(engine.url)}: {first_line(e)}")


def check_schema(engine: Engine, create: bool, allow_empty: bool = False, migrate: bool = False) -> str | None:
    """Refuse a database whose schema is not this code's head (see module doc).

    An empty database is created at head if ``create``, accepted untouched if
    ``allow_empty``, and refused otherwise.  A database at an older revision is
    migrated to head if ``migrate`` (``packings db upgrade``), else refused.
    Returns the revision the database had (None if it was empty).
    """
    where = display_url(engine.url)
    head = head_revision()
    try:
        with engine.connect() as conn:
            tables = set(inspect(conn).get_table_names())
        rev = current_revision(engine) if "alembic_version" in tables else None
    except OperationalError as e:
        raise connect_error(engine, e) from None
    if not tables:
        if allow_empty and not create:
            return None
        if not create:
            raise DatabaseError(f"{where} is empty: run `packings db upgrade` or `packings enumerate N` first")
        upgrade(engine)
        return None
    if rev is None:
        shown = ", ".join(sorted(tables)[:5])
        raise DatabaseError(f"{where} holds tables that are not a packings database ({shown}); use another database")
    if rev == head:
        return rev
    if rev in known_revisions():
        if migrate:
            upgrade(engine)
            return rev
        raise DatabaseError(f"{where} has schema {rev}, older than this code's {head}: run `packings db upgrade`")
    raise DatabaseError(f"{where} has schema {rev}, which this code does not know (newer?): upgrade packings")


def open_database(url: str, create: bool = False, migrate: bool = False) -> Engine:
    """Connect and check the schema; create an empty database at head if
    ``create``, and migrate an older one to head if ``migrate``.

    A SQLite file that does not exist is created only if ``create``; otherwise
    the error says so and nothing is written.
    """
    engine = make_engine(url)
    _missing_sqlite_file(engine, create)
    try:
        check_schema(engine, create, migrate=migrate)
    except DatabaseError:
        engine.dispose()
        raise
    except SQLAlchemyError as e:
        engine.dispose()
        raise connect_error(engine, e) from None
    return engine


def preflight(url: str, check: Callable[[Engine], None] | None = None) -> None:
    """Every check of :func:`open_database` that writes nothing: the URL, the
    connection, the schema (an empty or missing database passes); then, if the
    database has this code's schema, ``check`` on its engine (a caller's own
    check, which must only read: connections begin as readers)."""
    engine = make_engine(url).execution_options(**{READONLY: True})
    try:
        if _missing_sqlite_file(engine, create=True):
            return
        if check_schema(engine, create=False, allow_empty=True) is not None and check is not None:
            check(engine)
    except SQLAlchemyError as e:
        raise connect_error(engine, e) from None
    finally:
        engine.dispose()


def sessions(engine: Engine, readonly: bool = False) -> sessionmaker[Session]:
    """Sessions on ``engine``; ``readonly`` ones must not write, and every read of one sees the
    database as it was at its first: on SQLite they begin DEFERRED (a WAL snapshot, which never
    waits for, or blocks, a writer), on PostgreSQL REPEATABLE READ (under the default READ
    COMMITTED each statement would see the write-backs committed since the one before, and a
    page that counts clusters and expansions in two statements would disagree with itself)."""
    if readonly:
        options = {READONLY: True}
        if engine.dialect.name == "postgresql":
            options["isolation_level"] = "REPEATABLE READ"
        engine = engine.execution_options(**options)
    return sessionmaker(engine, expire_on_commit=False)
