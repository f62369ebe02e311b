"""clusters: the sticky-sphere partition function's geometric factor and symmetry number; attempts: rearranged

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-05 23:00:00

Six nullable columns of ``clusters`` (packings.workers.free_energy, docs/method.md): ``sigma`` (the
symmetry number), ``chiral``, ``log_z`` (log of z in Z = κ^m z; NULL where that formula does not apply,
``z_reason`` then saying why), ``eps_power`` and ``log_z_square_well`` (the leading term
Z = κ^m ε^eps_power e^log_z_square_well of a square well of width ε, where computed).  Rows stored before
this revision have ``sigma`` NULL until ``packings db upgrade`` (which runs the backfill) or
``packings db backfill`` computes them.

``attempts.rearranged``: of an expansion's paths, those that ended at the source with its spheres permuted
(outcome ``rearranged``, told from ``circular`` since this revision; 0 for the expansions stored before,
whose ``circular`` counts both).
"""

from typing import Sequence, Union

import numpy as np
import sqlalchemy as sa

from alembic import context, op
from packings.service.paths_codec import OUTCOMES, unpack

revision: str = "0010"
down_revision: Union[str, None] = "0009"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None

COLUMNS = (
    ("sigma", sa.Integer()),
    ("chiral", sa.Boolean()),
    ("log_z", sa.Float()),
    ("z_reason", sa.String(length=16)),
    ("eps_power", sa.Float()),
    ("log_z_square_well", sa.Float()),
)


_attempts = sa.table(
    "attempts", sa.column("id", sa.Integer), sa.column("data", sa.LargeBinary), sa.column("rearranged", sa.Integer)
)
BATCH = 500


def _count_rearranged(conn) -> None:
    """attempts.rearranged of the rows whose packed attempts hold the outcome, in batches of rows."""
    code = OUTCOMES.index("rearranged")
    last = 0
    while True:
        rows = conn.execute(
            sa.select(_attempts.c.id, _attempts.c.data)
            .where(_attempts.c.id > last)
            .order_by(_attempts.c.id)
            .limit(BATCH)
        ).all()
        if not rows:
            return
        for id_, data in rows:
            p = unpack(data)
            k = int(np.count_nonzero((p.outcome == code) & (p.direction != 0)))
            if k:
                conn.execute(sa.update(_attempts).where(_attempts.c.id == id_).values(rearranged=k))
        last = rows[-1].id


def upgrade() -> None:
    with op.batch_alter_table("clusters") as batch:
        for name, type_ in COLUMNS:
            batch.add_column(sa.Column(name, type_, nullable=True))
    with op.batch_alter_table("attempts") as batch:
        batch.add_column(sa.Column("rearranged", sa.Integer(), nullable=False, server_default="0"))
    if not context.is_offline_mode():  # rows packed with the outcome (a database taken down and up again)
        _count_rearranged(op.get_bind())


def downgrade() -> None:
    with op.batch_alter_table("attempts") as batch:
        batch.drop_column("rearranged")
    with op.batch_alter_table("clusters") as batch:
        for name, _ in reversed(COLUMNS):
            batch.drop_column(name)
