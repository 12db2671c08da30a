"""indexes on stage_result.parent_id and stage_result.run_id

Deleting a stage result (``rasterserver prune``) or a pipeline run makes the database check
that no stage result still names it as its parent or run. Without an index on those columns
that check reads the whole table for every row deleted: on SQLite, removing the 70,000
results of 10,000 acquisitions did not finish in 13 minutes (BENCHMARKS.md, "Reprocessing
throughput", 2026-11-27 (4)); with the indexes each check is a lookup.

Revision ID: 0013
Revises: 0012
Create Date: 2026-11-27 11:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0013"
down_revision: str | None = "0012"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("stage_result", schema=None) as batch_op:
        batch_op.create_index("ix_stage_result_parent", ["parent_id"], unique=False)
        batch_op.create_index("ix_stage_result_run", ["run_id"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("stage_result", schema=None) as batch_op:
        batch_op.drop_index("ix_stage_result_run")
        batch_op.drop_index("ix_stage_result_parent")
