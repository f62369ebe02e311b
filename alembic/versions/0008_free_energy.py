"""clusters: the sticky-sphere partition function's geometric factor and symmetry number

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-05 23:00:00

Six nullable columns of ``clusters`` (packings.workers.free_energy, docs/method.md): ``sigma`` (the
symmetry number), ``chiral``, ``log_z`` (log of z in Z = κ^m z; NULL where that formula does not apply,
``z_reason`` then saying why), ``eps_power`` and ``log_z_square_well`` (the leading term
Z = κ^m ε^eps_power e^log_z_square_well of a square well of width ε, where computed).  Rows stored before
this revision have ``sigma`` NULL until ``packings db upgrade`` (which runs the backfill) or
``packings db backfill`` computes them.
"""

from typing import Sequence, Union

import sqlalchemy as sa

from alembic import op

revision: str = "0008"
down_revision: Union[str, None] = "0007"
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


def upgrade() -> None:
    with op.batch_alter_table("clusters") as batch:
        for name, type_ in COLUMNS:
            batch.add_column(sa.Column(name, type_, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("clusters") as batch:
        for name, _ in reversed(COLUMNS):
            batch.drop_column(name)
