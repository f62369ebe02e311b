"""clusters.embedding in geometric order: the geometries of one contact graph numbered by shape

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-23 18:30:00

Until now the geometries of one contact graph were numbered 0, 1, ... in the order a run found
them, so two runs could give one (n, certificate, embedding) key different geometries.  They are
now numbered in embedding order (packings.workers.identity.embedding_position): pair distances
sorted from the largest down, compared one by one with a resolution of 4 tol_d (tol_d = 1e-5, the
default), the smaller first; geometries that agree within the resolution keep their old order.
This revision renumbers the stored clusters so; no schema changes.  Downgrade leaves the numbers
as they are (they are valid numbers under the old rule too).
"""

from typing import Sequence, Union

import numpy as np
import sqlalchemy as sa

from alembic import context, op

revision: str = "0005"
down_revision: Union[str, None] = "0004"
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None

#: 4 tol_d at the default tol_d: the rule's resolution, written here so that this revision keeps
#: meaning what it meant when later code changes
RESOLUTION = 4e-5


def _sorted_distances(n: int, coords: bytes) -> np.ndarray:
    x = np.frombuffer(coords, dtype="<f8").reshape(n, 3)
    i, j = np.triu_indices(n, 1)
    return np.sort(np.linalg.norm(x[i] - x[j], axis=1))


def _precedes(a: np.ndarray, b: np.ndarray) -> bool:
    differ = np.flatnonzero(np.abs(a - b) > RESOLUTION)
    return bool(differ.size) and bool(a[differ[-1]] < b[differ[-1]])


def upgrade() -> None:
    if context.is_offline_mode():  # the new numbers come from the stored coordinates
        op.execute(
            "-- 0005 renumbers clusters.embedding from the stored coordinates: run it on the database "
            "(packings db upgrade); an empty database has nothing to renumber"
        )
        return
    bind = op.get_bind()
    groups = bind.execute(
        sa.text("SELECT n, certificate FROM clusters GROUP BY n, certificate HAVING count(*) > 1")
    ).all()
    for n, cert in groups:
        rows = bind.execute(
            sa.text("SELECT id, coords FROM clusters WHERE n = :n AND certificate = :cert ORDER BY embedding"),
            {"n": n, "cert": cert},
        ).all()
        ordered: list[tuple[int, np.ndarray]] = []
        for id_, coords in rows:  # inserted one by one in the old order, as the store inserts them
            d = _sorted_distances(n, bytes(coords))
            k = next((k for k, (_, o) in enumerate(ordered) if _precedes(d, o)), len(ordered))
            ordered.insert(k, (id_, d))
        # through negative numbers, so that no two rows share a key between two statements
        for k, (id_, _) in enumerate(ordered):
            bind.execute(sa.text("UPDATE clusters SET embedding = :e WHERE id = :id"), {"e": -1 - k, "id": id_})
        bind.execute(
            sa.text("UPDATE clusters SET embedding = -1 - embedding WHERE n = :n AND certificate = :cert"),
            {"n": n, "cert": cert},
        )


def downgrade() -> None:
    pass
