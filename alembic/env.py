"""Alembic environment: migrations for the packings schema (packings.service.models).

``packings db upgrade`` passes an open connection in ``config.attributes``;
the ``alembic`` command (with the repository's ``alembic.ini``, whose logging
setup it applies) uses ``-x db=URL``, else ``sqlalchemy.url``, online and
with ``--sql`` alike.

SQLite: a migration that rebuilds a table (batch mode: copy, drop, rename)
cannot drop a table that other tables' rows refer to while foreign keys are
enforced, and SQLite only switches them off outside a transaction.  So they
are off for the migration, on the connection it runs on, and after it
``PRAGMA foreign_key_check`` must find nothing before they are on again.
"""

from logging.config import fileConfig

from alembic import context
from packings.service.db import make_engine
from packings.service.models import Base

config = context.config
target_metadata = Base.metadata

if config.config_file_name is not None and "connection" not in config.attributes:
    fileConfig(config.config_file_name, disable_existing_loggers=False)


def _url() -> str:
    return context.get_x_argument(as_dictionary=True).get("db") or config.get_main_option("sqlalchemy.url")


def _configure(connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",
        compare_type=True,
    )


def _migrate(connection) -> None:
    """Run the migrations on ``connection`` (not in a transaction yet), in one transaction."""
    sqlite = connection.dialect.name == "sqlite"
    if sqlite:
        if connection.in_transaction():
            raise RuntimeError("SQLite migrations need a connection outside a transaction (foreign keys off)")
        connection.connection.driver_connection.execute("PRAGMA foreign_keys=OFF")
    try:
        _configure(connection)
        with context.begin_transaction():
            context.run_migrations()
            if sqlite:
                broken = connection.exec_driver_sql("PRAGMA foreign_key_check").fetchall()
                if broken:
                    raise RuntimeError(f"the migration left rows whose references are broken: {broken[:5]}")
        if connection.in_transaction():
            connection.commit()
    finally:
        if sqlite:
            connection.connection.driver_connection.execute("PRAGMA foreign_keys=ON")


def run_migrations_offline() -> None:
    context.configure(
        url=_url(),
        target_metadata=target_metadata,
        literal_binds=True,
        dialect_opts={"paramstyle": "named"},
        render_as_batch=_url().startswith("sqlite"),
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _migrate(connection)
        return
    engine = make_engine(_url())
    try:
        with engine.connect() as conn:
            _migrate(conn)
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
