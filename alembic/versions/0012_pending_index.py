"""ix_expansions_pending: the pending expansions of a run in the order they are claimed

Revision ID: 0012
Revises: 0011
Create Date: 2026-12-06 12:20:00

A claim takes a run's pending expansions lowest id first (packings.service.store.claim). PostgreSQL
could not read them in that order from ``ix_expansions_run_status``, whose entries of one status follow
the table's storage, not the ids: it walked the primary key instead and skipped every expansion done,
so a claim cost grew with the run (tens of milliseconds with a few hundred thousand done). This partial
index holds only the pending expansions, by (run_id, id): a claim reads its k entries and no more, on
both backends, and a complete run's index is empty.
"""

from typing import Sequence, Union

import sqlalchemy as sa

from alembic import op

revision: str = "0012"
down_revision: Union[str, None] = "0011"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None

PENDING = sa.text("status = 'pending'")


def upgrade() -> None:
    op.create_index(
        "ix_expansions_pending", "expansions", ["run_id", "id"], postgresql_where=PENDING, sqlite_where=PENDING
    )


def downgrade() -> None:
    op.drop_index("ix_expansions_pending", table_name="expansions")
