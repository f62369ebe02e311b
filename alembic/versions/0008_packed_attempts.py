"""attempts and edges: one packed row per expansion instead of one row per attempt

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-05 23:00:00

``transitions`` kept one row per attempt (about 120 bytes with its three indexes: 80 % of a large
run's database).  Its rows become one ``attempts`` row per (run, source cluster), the attempts packed
by :mod:`packings.service.paths_codec` (version 1) in the order of their transitions' ids, the rows in
the order of each expansion's first transition (the order they were written, which is the order a
task reads its arrivals in); and one ``edges`` row per (target, source, run) with the number of
attempts that reached the target and how many carry labels.  The downgrade unpacks them back into
``transitions`` (new ids, in the same order).  Both go in batches of expansions.
"""

import json
from typing import Sequence, Union

import sqlalchemy as sa

from alembic import context, op
from packings.service.paths_codec import OUTCOMES, Attempt, pack, summary, unpack

revision: str = "0008"
down_revision: Union[str, None] = "0007"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None

BATCH = 500  #: expansions converted at once

_transitions = sa.table(
    "transitions",
    sa.column("id", sa.Integer),
    sa.column("run_id", sa.Integer),
    sa.column("source_id", sa.Integer),
    sa.column("broken", sa.Text),
    sa.column("direction", sa.Integer),
    sa.column("outcome", sa.String),
    sa.column("target_id", sa.Integer),
    sa.column("steps", sa.Integer),
    sa.column("new_contacts", sa.Text),
    sa.column("target_labels", sa.Text),
)
_clusters = sa.table("clusters", sa.column("id", sa.Integer), sa.column("n", sa.Integer))
_attempts = sa.table(
    "attempts",
    sa.column("id", sa.Integer),
    sa.column("run_id", sa.Integer),
    sa.column("source_id", sa.Integer),
    sa.column("attempts", sa.Integer),
    sa.column("paths", sa.Integer),
    sa.column("circular", sa.Integer),
    sa.column("data", sa.LargeBinary),
)
_edges = sa.table(
    "edges",
    sa.column("target_id", sa.Integer),
    sa.column("source_id", sa.Integer),
    sa.column("run_id", sa.Integer),
    sa.column("paths", sa.Integer),
    sa.column("labelled", sa.Integer),
)


def _create_attempts_and_edges() -> None:
    op.create_table(
        "attempts",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("source_id", sa.Integer(), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("paths", sa.Integer(), nullable=False),
        sa.Column("circular", sa.Integer(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"]),
        sa.ForeignKeyConstraint(["source_id"], ["clusters.id"]),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("source_id", "run_id", name="uq_attempts_source_run"),
    )
    op.create_table(
        "edges",
        sa.Column("target_id", sa.Integer(), nullable=False),
        sa.Column("source_id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("paths", sa.Integer(), nullable=False),
        sa.Column("labelled", sa.Integer(), nullable=False),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"]),
        sa.ForeignKeyConstraint(["source_id"], ["clusters.id"]),
        sa.ForeignKeyConstraint(["target_id"], ["clusters.id"]),
        sa.PrimaryKeyConstraint("target_id", "source_id", "run_id"),
        sqlite_with_rowid=False,
    )


def _create_transitions() -> None:
    """``transitions`` as revisions 0001 and 0006 left it."""
    op.create_table(
        "transitions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("source_id", sa.Integer(), nullable=False),
        sa.Column("broken", sa.Text(), nullable=False),
        sa.Column("direction", sa.Integer(), nullable=False),
        sa.Column("outcome", sa.String(length=32), nullable=False),
        sa.Column("target_id", sa.Integer(), nullable=True),
        sa.Column("steps", sa.Integer(), nullable=False),
        sa.Column("new_contacts", sa.Text(), nullable=False),
        sa.Column("target_labels", sa.Text(), nullable=True),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"]),
        sa.ForeignKeyConstraint(["source_id"], ["clusters.id"]),
        sa.ForeignKeyConstraint(["target_id"], ["clusters.id"]),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("run_id", "source_id", "broken", "direction", name="uq_transitions_attempt"),
    )
    op.create_index("ix_transitions_target", "transitions", ["target_id"], unique=False)
    op.create_index("ix_transitions_source", "transitions", ["source_id"], unique=False)


def _pairs(text: str) -> tuple[tuple[int, int], ...]:
    return tuple((int(i), int(j)) for i, j in json.loads(text))


def _json(pairs) -> str:
    return "[" + ", ".join(f"[{int(i)}, {int(j)}]" for i, j in pairs) + "]"


_OFFLINE = (
    "transitions rows are packed only by an upgrade on the database itself (packings db upgrade), "
    "not by the SQL of --sql"
)


def upgrade() -> None:
    if context.is_offline_mode():  # SQL for an empty database: the rows cannot be packed in SQL
        if op.get_context().dialect.name == "postgresql":
            op.execute(
                f"DO $$ BEGIN IF EXISTS (SELECT 1 FROM transitions) THEN RAISE EXCEPTION '{_OFFLINE}'; END IF; END $$"
            )
        else:
            op.execute(f"-- {_OFFLINE}: run it on an empty transitions table only")
        _create_attempts_and_edges()
        op.drop_index("ix_transitions_target", table_name="transitions")
        op.drop_index("ix_transitions_source", table_name="transitions")
        op.drop_table("transitions")
        return
    conn = op.get_bind()
    unknown = set(conn.execute(sa.select(_transitions.c.outcome).distinct()).scalars()) - set(OUTCOMES)
    if unknown:
        raise RuntimeError(f"transitions with outcomes this code does not know: {', '.join(sorted(unknown))}")
    _create_attempts_and_edges()
    # the expansions in the order they were written (the first id of each), with their cluster's n
    first = sa.func.min(_transitions.c.id).label("first")
    groups = conn.execute(
        sa.select(_transitions.c.run_id, _transitions.c.source_id, _clusters.c.n, first)
        .join(_clusters, _clusters.c.id == _transitions.c.source_id)
        .group_by(_transitions.c.run_id, _transitions.c.source_id, _clusters.c.n)
        .order_by(first)
    ).all()
    for start in range(0, len(groups), BATCH):
        batch = groups[start : start + BATCH]
        sources = sorted({g.source_id for g in batch})
        rows: dict[tuple[int, int], list] = {(g.run_id, g.source_id): [] for g in batch}
        for t in conn.execute(
            sa.select(_transitions).where(_transitions.c.source_id.in_(sources)).order_by(_transitions.c.id)
        ):
            if (t.run_id, t.source_id) in rows:
                rows[(t.run_id, t.source_id)].append(
                    Attempt(
                        _pairs(t.broken),
                        int(t.direction),
                        t.outcome,
                        t.target_id,
                        int(t.steps),
                        _pairs(t.new_contacts),
                        None if t.target_labels is None else tuple(int(k) for k in json.loads(t.target_labels)),
                    )
                )
        packed, edges = [], []
        for g in batch:
            attempts = rows[(g.run_id, g.source_id)]
            sm = summary(attempts)
            packed.append(
                {
                    "run_id": g.run_id,
                    "source_id": g.source_id,
                    "attempts": sm.attempts,
                    "paths": sm.paths,
                    "circular": sm.circular,
                    "data": pack(g.n, attempts),
                }
            )
            edges += [
                {"target_id": t, "source_id": g.source_id, "run_id": g.run_id, "paths": p, "labelled": lab}
                for t, (p, lab) in sorted(sm.edges.items())
            ]
        conn.execute(_attempts.insert(), packed)
        if edges:
            conn.execute(_edges.insert(), edges)
    op.drop_index("ix_transitions_target", table_name="transitions")
    op.drop_index("ix_transitions_source", table_name="transitions")
    op.drop_table("transitions")


def downgrade() -> None:
    _create_transitions()
    if context.is_offline_mode():
        op.execute("-- attempts rows are unpacked only by a downgrade on the database itself")
        op.drop_table("edges")
        op.drop_table("attempts")
        return
    conn = op.get_bind()
    last = 0
    while True:
        batch = conn.execute(
            sa.select(_attempts.c.id, _attempts.c.run_id, _attempts.c.source_id, _attempts.c.data)
            .where(_attempts.c.id > last)
            .order_by(_attempts.c.id)
            .limit(BATCH)
        ).all()
        if not batch:
            break
        rows = [
            {
                "run_id": r.run_id,
                "source_id": r.source_id,
                "broken": _json(a.broken),
                "direction": a.direction,
                "outcome": a.outcome,
                "target_id": a.target,
                "steps": a.steps,
                "new_contacts": _json(a.new_contacts),
                "target_labels": None if a.labels is None else json.dumps(list(a.labels)),
            }
            for r in batch
            for a in unpack(r.data)
        ]
        if rows:
            conn.execute(_transitions.insert(), rows)
        last = batch[-1].id
    op.drop_table("edges")
    op.drop_table("attempts")
