"""Database fixtures: every database test runs on SQLite and on a real PostgreSQL.

PostgreSQL is reached through ``PACKINGS_TEST_PG`` (an admin URL, default
``postgresql://postgres@127.0.0.1:5432/postgres``); each test gets a fresh
database, dropped afterwards.  Without a server the PostgreSQL variants skip
with the reason, unless ``PACKINGS_REQUIRE_PG=1`` (set by ``.ci/run``), in
which case they fail.
"""

from __future__ import annotations

import os
from contextlib import contextmanager

import pytest

PG_ADMIN = os.environ.get("PACKINGS_TEST_PG", "postgresql://postgres@127.0.0.1:5432/postgres")
_pg_problem: list[str] = []


def _pg_admin_engine():
    from sqlalchemy import create_engine

    from packings.service.db import parse_url

    return create_engine(parse_url(PG_ADMIN), isolation_level="AUTOCOMMIT")


def _pg_available() -> str | None:
    """None if PostgreSQL answers, else why not."""
    if not _pg_problem:
        try:
            from sqlalchemy import text

            eng = _pg_admin_engine()
            with eng.connect() as c:
                c.execute(text("SELECT 1"))
            eng.dispose()
            _pg_problem.append("")
        except Exception as e:  # noqa: BLE001 - any failure means "no server here"
            _pg_problem.append(
                f"no PostgreSQL at {PG_ADMIN} ({str(e).splitlines()[0][:120]}); "
                "set PACKINGS_TEST_PG to an admin URL to run these tests"
            )
    return _pg_problem[0] or None


@contextmanager
def pg_database():
    """A fresh, empty PostgreSQL database (URL) at any scope, dropped on leaving;
    skips (or fails, under PACKINGS_REQUIRE_PG=1) without a server."""
    from benchmarks.soak import postgresql_database

    problem = _pg_available()
    if problem:
        if os.environ.get("PACKINGS_REQUIRE_PG") == "1":
            pytest.fail(problem)
        pytest.skip(problem)
    with postgresql_database(PG_ADMIN, "packings_test") as url:
        yield url


@pytest.fixture
def pg_url():
    """A fresh, empty PostgreSQL database (URL), dropped after the test."""
    with pg_database() as url:
        yield url


@pytest.fixture
def sqlite_url(tmp_path):
    """A SQLite file that does not exist yet (URL)."""
    return f"sqlite:///{tmp_path / 'packings.db'}"


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request):
    """An empty database on each backend (URL)."""
    if request.param == "sqlite":
        return request.getfixturevalue("sqlite_url")
    return request.getfixturevalue("pg_url")


@pytest.fixture
def engine(db_url):
    """An open engine on a fresh database at the schema's head."""
    from packings.service.db import open_database

    eng = open_database(db_url, create=True)
    yield eng
    eng.dispose()


def fill_database(engine, n: int, params=None, owner: str = "test:0:inline") -> int:
    """Run the whole enumeration of n in this process (no Dask), through the
    same store functions the service uses; returns the run id."""
    from packings.service import store
    from packings.service.db import sessions
    from packings.service.tasks import run_expansion
    from packings.workers.params import Params

    Session_ = sessions(engine)
    info = store.start_run(Session_, n, params or Params(), owner)
    while True:
        batch = store.claim(Session_, info.id, owner, 8)
        if not batch:
            break
        for eid, token in batch:
            run_expansion(Session_, eid, token)
    store.finish_run(Session_, info.id, owner, 0.0)
    return info.id


@pytest.fixture
def filled(engine):
    """A database holding the complete enumeration of n = 7 (5 clusters) and n = 8 (13 clusters)."""
    fill_database(engine, 7)
    fill_database(engine, 8)
    return engine
