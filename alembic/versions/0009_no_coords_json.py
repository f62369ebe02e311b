"""clusters.coords_json dropped: the coordinates are stored once, in clusters.coords

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-05 23:30:00

``coords_json`` held the numbers of ``coords`` (n x 3 little-endian float64) again as JSON text, about
530 bytes a cluster at n = 11: a third of the clusters table, and more than a quarter of a database
once the attempts are packed (0008).  ``packings export`` and the Python API give the coordinates as
numbers.  The downgrade writes the column again from ``coords``, as the service wrote it
(``json.dumps`` of the float64 array's list: the shortest repr of each number).  A SQLite file keeps
its size until ``VACUUM``.
"""

import json
import sqlite3
from typing import Sequence, Union

import numpy as np
import sqlalchemy as sa

from alembic import context, op

revision: str = "0009"
down_revision: Union[str, None] = "0008"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None

BATCH = 5000  #: clusters written at once by the downgrade

_clusters = sa.table(
    "clusters",
    sa.column("id", sa.Integer),
    sa.column("n", sa.Integer),
    sa.column("coords", sa.LargeBinary),
    sa.column("coords_json", sa.Text),
)


def _sqlite_in_place() -> bool:
    """SQLite drops a column in place from 3.35 on (a batch operation would copy the table)."""
    return sqlite3.sqlite_version_info >= (3, 35, 0)


def upgrade() -> None:
    if op.get_context().dialect.name == "sqlite" and _sqlite_in_place():
        op.execute("ALTER TABLE clusters DROP COLUMN coords_json")
    else:
        with op.batch_alter_table("clusters") as batch:
            batch.drop_column("coords_json")


def downgrade() -> None:
    sqlite = op.get_context().dialect.name == "sqlite"
    # SQLite adds a NOT NULL column in place only with a default
    op.add_column(
        "clusters", sa.Column("coords_json", sa.Text(), nullable=not sqlite, server_default="" if sqlite else None)
    )
    if not context.is_offline_mode():
        conn = op.get_bind()
        last = 0
        while rows := conn.execute(
            sa.select(_clusters.c.id, _clusters.c.n, _clusters.c.coords)
            .where(_clusters.c.id > last)
            .order_by(_clusters.c.id)
            .limit(BATCH)
        ).all():
            conn.execute(
                _clusters.update().where(_clusters.c.id == sa.bindparam("cid")),
                [
                    {
                        "cid": cid,
                        "coords_json": json.dumps(np.frombuffer(coords, dtype="<f8").reshape(n, 3).tolist()),
                    }
                    for cid, n, coords in rows
                ],
            )
            last = rows[-1].id
    if not sqlite:
        op.alter_column("clusters", "coords_json", nullable=False)
