"""clusters.contact_list (JSON text) becomes clusters.contact_pairs: two bytes a contact

Revision ID: 0011
Revises: 0010
Create Date: 2026-12-06 09:10:00

A cluster's contacts were JSON text, ``[[0, 1], [0, 2], ...]``: about 280 bytes at n = 13, a third of
the clusters table. ``contact_pairs`` holds the same pairs as bytes, ``i`` and ``j`` one unsigned byte
each (n is at most 24), in the same order: a quarter of the size. The service reads and writes it as the
same JSON text (packings.service.models.ContactPairs), so that nothing it gives changes. The downgrade
writes ``contact_list`` again as the service wrote it (``json.dumps`` of the pairs). A SQLite file keeps
its size until ``VACUUM``.
"""

import json
import sqlite3
from typing import Sequence, Union

import sqlalchemy as sa

from alembic import context, op

revision: str = "0011"
down_revision: Union[str, None] = "0010"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None

BATCH = 5000  #: clusters converted at once

_clusters = sa.table(
    "clusters",
    sa.column("id", sa.Integer),
    sa.column("contact_list", sa.Text),
    sa.column("contact_pairs", sa.LargeBinary),
)


def _pack(text: str) -> bytes:
    return bytes(int(k) for pair in json.loads(text) for k in pair)


def _unpack(packed: bytes) -> str:
    packed = bytes(packed)
    return json.dumps([[packed[k], packed[k + 1]] for k in range(0, len(packed), 2)])


def _add(name: str, type_, empty) -> None:
    """A NOT NULL column added (SQLite adds one in place only with a default: ``empty``)."""
    sqlite = op.get_context().dialect.name == "sqlite"
    op.add_column("clusters", sa.Column(name, type_, nullable=not sqlite, server_default=empty if sqlite else None))


def _convert(source: str, target: str, f) -> None:
    """``target = f(source)`` for every cluster, in batches by id."""
    if context.is_offline_mode():
        return
    conn = op.get_bind()
    src, dst = _clusters.c[source], _clusters.c[target]
    last = 0
    while rows := conn.execute(
        sa.select(_clusters.c.id, src).where(_clusters.c.id > last).order_by(_clusters.c.id).limit(BATCH)
    ).all():
        conn.execute(
            _clusters.update().where(_clusters.c.id == sa.bindparam("cid")),
            [{"cid": cid, dst.name: f(value)} for cid, value in rows],
        )
        last = rows[-1][0]


def _drop(name: str) -> None:
    """SQLite drops a column in place from 3.35 on (a batch operation would copy the table)."""
    if op.get_context().dialect.name == "sqlite" and sqlite3.sqlite_version_info >= (3, 35, 0):
        op.execute(f"ALTER TABLE clusters DROP COLUMN {name}")
    else:
        with op.batch_alter_table("clusters") as batch:
            batch.drop_column(name)


def _finish(name: str) -> None:
    if op.get_context().dialect.name != "sqlite":
        op.alter_column("clusters", name, nullable=False)


def upgrade() -> None:
    _add("contact_pairs", sa.LargeBinary(), sa.text("x''"))
    _convert("contact_list", "contact_pairs", _pack)
    _finish("contact_pairs")
    _drop("contact_list")


def downgrade() -> None:
    _add("contact_list", sa.Text(), "")
    _convert("contact_pairs", "contact_list", _unpack)
    _finish("contact_list")
    _drop("contact_pairs")
