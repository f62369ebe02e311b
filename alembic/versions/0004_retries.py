"""expansions.retries and expansions.isolated_failures: infrastructure faults are not attempts

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-23 16:00:00

retries counts the times an expansion was put back to pending because its task was lost with
its worker (or its coordinator was), without using up an attempt; isolated_failures the times
its task, run alone after such a fault, was lost again, which counts as an attempt
(packings.service.coordinator).  Existing rows start at 0.
"""

from typing import Sequence, Union

import sqlalchemy as sa

from alembic import op

revision: str = "0004"
down_revision: Union[str, None] = "0003"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None


def upgrade() -> None:
    # plain ADD COLUMN on both backends (SQLite adds a NOT NULL column with a default in place)
    op.add_column("expansions", sa.Column("retries", sa.Integer(), nullable=False, server_default="0"))
    op.add_column("expansions", sa.Column("isolated_failures", sa.Integer(), nullable=False, server_default="0"))


def downgrade() -> None:
    # plain DROP COLUMN on both backends (SQLite 3.35+ drops a column without constraints in place;
    # batch mode would rebuild the table)
    op.execute("ALTER TABLE expansions DROP COLUMN isolated_failures")
    op.execute("ALTER TABLE expansions DROP COLUMN retries")
