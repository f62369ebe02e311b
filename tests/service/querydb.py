"""A filled database shared by the tests of one module (the query side only reads).

``catalog = filled_catalog(7, 8)`` in a test module gives a module-scoped
fixture: on SQLite and on PostgreSQL (as the ``engine`` fixture of conftest),
a database holding the complete enumerations of those n, filled once.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass

import pytest
from sqlalchemy import Engine

from tests.service.conftest import fill_database, pg_database


@dataclass
class Catalog:
    engine: Engine
    runs: dict[int, int]  #: n -> run id

    @property
    def url(self) -> str:
        return str(self.engine.url.render_as_string(hide_password=False))


def filled_catalog(*ns: int):
    """A module-scoped fixture: a :class:`Catalog` holding the enumerations of ``ns``, on each backend."""

    @pytest.fixture(scope="module", params=["sqlite", "postgresql"])
    def catalog(request, tmp_path_factory):
        from packings.service.db import open_database

        if request.param == "sqlite":
            database = nullcontext(f"sqlite:///{tmp_path_factory.mktemp('catalog') / 'packings.db'}")
        else:
            database = pg_database()
        with database as url:
            engine = open_database(url, create=True)
            try:
                yield Catalog(engine, {n: fill_database(engine, n) for n in ns})
            finally:
                engine.dispose()

    return catalog
