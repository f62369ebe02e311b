"""Database fixtures: every database test runs on SQLite and on a real PostgreSQL.

PostgreSQL is reached through ``PACKINGS_TEST_PG`` (an admin URL, default
``postgresql://postgres@127.0.0.1:5432/postgres``); each test gets a fresh
database, dropped afterwards.  Without a server the PostgreSQL variants skip
with the reason, unless ``PACKINGS_REQUIRE_PG=1`` (set by ``.ci/run``), in
which case they fail.
"""

from __future__ import annotations

import pytest

from tests.helpers import catalogue, fill_database, pg_database


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


@pytest.fixture
def filled(engine):
    """A database holding the complete enumeration of n = 7 (5 clusters) and n = 8 (13 clusters)."""
    fill_database(engine, 7)
    fill_database(engine, 8)
    return engine


@pytest.fixture(scope="module")
def reference10():
    """The serial in-memory enumeration of n = 10 (packings.workers.explore): one order of discovery."""
    return list(catalogue(10).clusters)
