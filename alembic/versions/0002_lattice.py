"""clusters.lattice: the close-packed lattice a cluster is a fragment of; transitions by source

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-21 12:00:00

The column holds packings.workers.classify's label (fcc, hcp, both, random, 2d) or
'none'; it is NULL for clusters stored before this revision until
``packings db upgrade`` (which runs the backfill) or ``packings db backfill``
computes it.
"""

from typing import Sequence, Union

import sqlalchemy as sa

from alembic import op

revision: str = "0002"
down_revision: Union[str, None] = "0001"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None


def upgrade() -> None:
    op.add_column("clusters", sa.Column("lattice", sa.String(length=16), nullable=True))
    op.create_index("ix_clusters_n_lattice", "clusters", ["n", "lattice"], unique=False)
    op.create_index("ix_transitions_source", "transitions", ["source_id"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_transitions_source", table_name="transitions")
    op.drop_index("ix_clusters_n_lattice", table_name="clusters")
    with op.batch_alter_table("clusters") as batch:
        batch.drop_column("lattice")
