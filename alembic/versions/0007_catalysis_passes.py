"""catalysis_passes: the catalysis passes that ran to their end

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-29 09:00:00

One row per catalysis pass that ran to its end: the run its finds went to, how its parents' remainders
were made (``glued`` or ``deleted``), the spheres deleted, and the parents it read (the stored clusters
with an id above ``after``, up to ``last_parent``).  ``packings enumerate N --glued`` takes as the
parents of its next pass only the clusters stored since.
"""

from typing import Sequence, Union

import sqlalchemy as sa

from alembic import op

revision: str = "0007"
down_revision: Union[str, None] = "0006"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None


def upgrade() -> None:
    op.create_table(
        "catalysis_passes",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=16), nullable=False),
        sa.Column("spheres", sa.Integer(), nullable=False),
        sa.Column("after", sa.Integer(), nullable=False),
        sa.Column("last_parent", sa.Integer(), nullable=True),
        sa.Column("parents", sa.Integer(), nullable=False),
        sa.Column("remainders", sa.Integer(), nullable=False),
        sa.Column("rigid", sa.Integer(), nullable=False),
        sa.Column("new", sa.Integer(), nullable=False),
        sa.Column("started_at", sa.DateTime(), nullable=False),
        sa.Column("finished_at", sa.DateTime(), nullable=False),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"]),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index(op.f("ix_catalysis_passes_run_id"), "catalysis_passes", ["run_id"], unique=False)


def downgrade() -> None:
    op.drop_index(op.f("ix_catalysis_passes_run_id"), table_name="catalysis_passes")
    op.drop_table("catalysis_passes")
