"""clusters.found_by and clusters.source_id: how a cluster was first found, and from which cluster

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23 10:00:00

found_by is 'seed' (the starting cluster of a run), 'path' (the endpoint of a path from
source_id, the cluster whose expansion found it) or 'catalysis' (a remainder of source_id, a
cluster of more spheres, after deleting spheres: packings.service.catalysis).

Rows stored before this revision are backfilled from the expansions and transitions: the
cluster of a run's first expansion, if that run stored it, is the run's seed ('seed', no source;
other clusters' paths may reach a seed later, so being reached is no test); every other cluster
is 'path', with source_id the source of the first transition from another cluster that reached
it (written in the transaction that stored it: a later one needs the committed row's id); a
cluster that neither rule places (none is expected) is 'seed' with no source.  found_by keeps the server default 'path'
that gave existing rows a value (SQLite cannot drop it without rebuilding the table); the service
names found_by in every insert.
"""

from typing import Sequence, Union

import sqlalchemy as sa

from alembic import op

revision: str = "0003"
down_revision: Union[str, None] = "0002"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None


def upgrade() -> None:
    # Plain ALTER TABLE ... ADD COLUMN on both backends: SQLite adds a column with an inline REFERENCES
    # (and a NOT NULL column with a default) in place, where batch mode would rebuild the table, which
    # with foreign keys on (packings.db) cannot be dropped while expansions and transitions refer to it.
    op.add_column("clusters", sa.Column("found_by", sa.String(length=16), nullable=False, server_default="path"))
    if op.get_bind().dialect.name == "sqlite":  # Alembic adds no constraint to a SQLite table in place
        op.execute(
            "ALTER TABLE clusters ADD COLUMN source_id INTEGER "
            "CONSTRAINT fk_clusters_source_id REFERENCES clusters (id)"
        )
    else:
        op.add_column(
            "clusters",
            sa.Column(
                "source_id", sa.Integer(), sa.ForeignKey("clusters.id", name="fk_clusters_source_id"), nullable=True
            ),
        )
    op.create_index("ix_clusters_source", "clusters", ["source_id"], unique=False)
    # a run's seed: the cluster of its first expansion, if the run stored it (start_run)
    # (the first expansions of all runs found once, not once per cluster: a correlated form of this
    # query took minutes on an n = 12 catalogue)
    op.execute(
        "UPDATE clusters SET found_by = 'seed' WHERE id IN (SELECT e.cluster_id FROM expansions e "
        "JOIN (SELECT run_id, min(id) AS first_id FROM expansions GROUP BY run_id) f ON e.id = f.first_id "
        "JOIN clusters c ON c.id = e.cluster_id AND c.found_in_run = e.run_id)"
    )
    op.execute(
        "UPDATE clusters SET source_id = (SELECT t.source_id FROM transitions t "
        "WHERE t.target_id = clusters.id AND t.source_id <> clusters.id ORDER BY t.id LIMIT 1) "
        "WHERE found_by = 'path'"
    )
    op.execute("UPDATE clusters SET found_by = 'seed' WHERE source_id IS NULL")


def downgrade() -> None:
    op.drop_index("ix_clusters_source", table_name="clusters")
    if op.get_bind().dialect.name == "sqlite":
        # SQLite drops a column in place (3.35+), but not one with a REFERENCES clause: rebuild the table
        # (as 0002's downgrade does; env.py switches foreign keys off around it, so rows that refer to
        # clusters do not stop it)
        with op.batch_alter_table("clusters", recreate="always") as batch:
            batch.drop_column("source_id")
            batch.drop_column("found_by")
        return
    op.drop_constraint("fk_clusters_source_id", "clusters", type_="foreignkey")
    op.drop_column("clusters", "source_id")
    op.drop_column("clusters", "found_by")
