"""transitions.target_labels: how a path's endpoint is labelled as the stored target

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-27 17:10:00

A path from a regular cluster A that breaks one contact and ends at a regular cluster B by forming one
is retraced by B's path that breaks the contact formed: a run takes that path's transition from the
one that arrived instead of following it again (docs/method.md).
For that it keeps, with such a transition, the relabelling of its endpoint onto B as stored: sphere i
of the endpoint is sphere target_labels[i] of B (JSON).  Rows stored before stay NULL: their paths are
followed again where needed.
"""

from typing import Sequence, Union

import sqlalchemy as sa

from alembic import op

revision: str = "0006"
down_revision: Union[str, None] = "0005"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None


def upgrade() -> None:
    # a plain ALTER TABLE ... ADD COLUMN: a run's transitions table holds millions of rows, and a batch
    # operation could copy it on SQLite
    op.add_column("transitions", sa.Column("target_labels", sa.Text(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("transitions") as batch:
        batch.drop_column("target_labels")
