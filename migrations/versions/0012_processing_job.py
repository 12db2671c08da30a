"""processing jobs in the catalogue: processing_job and processing_task

A processing job (``rasterserver process``, ``POST /jobs``) is a row, and every acquisition it
resolved to is a task row, created with it in one transaction. A job outlives the process that
runs it: ``rasterserver jobs resume`` continues with the tasks still ``pending``, and
``rasterserver jobs pause|cancel`` stop it from another process. HTTP jobs used ``api_job``
(revision 0003), which stays for the history of the jobs before this revision; new jobs are
here.

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-24 10:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0012"
down_revision: str | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "processing_job",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("origin", sa.String(length=16), nullable=False),
        sa.Column("owner", sa.String(length=100), nullable=False),
        sa.Column("selection", sa.JSON(), nullable=False),
        sa.Column("chain", sa.JSON(), nullable=False),
        sa.Column("targets", sa.JSON(), nullable=False),
        sa.Column("engine", sa.String(length=300), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("total", sa.Integer(), nullable=False),
        sa.Column("done", sa.Integer(), nullable=False),
        sa.Column("failed", sa.Integer(), nullable=False),
        sa.Column("runner", sa.String(length=300), nullable=False),
        sa.Column("error", sa.Text(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("resumed_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("resumed_count", sa.Integer(), nullable=False),
        sa.Column("progress_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.CheckConstraint(
            "state IN ('queued', 'running', 'paused', 'cancelled', 'done', 'failed')",
            name=op.f("ck_processing_job_state"),
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_processing_job")),
    )
    with op.batch_alter_table("processing_job", schema=None) as batch_op:
        batch_op.create_index("ix_processing_job_created_at", ["created_at"], unique=False)
        batch_op.create_index("ix_processing_job_state", ["state"], unique=False)
    op.create_table(
        "processing_task",
        sa.Column("job_id", sa.String(length=32), nullable=False),
        sa.Column("position", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("uid", sa.Text(), nullable=False),
        sa.Column("acquisition_id", sa.Integer(), nullable=True),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("computed", sa.Integer(), nullable=False),
        sa.Column("reused", sa.Integer(), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.Column("error", sa.Text(), nullable=False),
        sa.Column("exit_code", sa.Integer(), nullable=False),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.CheckConstraint(
            "state IN ('pending', 'done', 'failed')", name=op.f("ck_processing_task_state")
        ),
        sa.ForeignKeyConstraint(
            ["job_id"],
            ["processing_job.id"],
            name=op.f("fk_processing_task_job_id_processing_job"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["acquisition_id"],
            ["acquisition.id"],
            name=op.f("fk_processing_task_acquisition_id_acquisition"),
            ondelete="RESTRICT",
        ),
        sa.PrimaryKeyConstraint("job_id", "position", name=op.f("pk_processing_task")),
    )
    with op.batch_alter_table("processing_task", schema=None) as batch_op:
        batch_op.create_index(
            "ix_processing_task_job_state", ["job_id", "state", "position"], unique=False
        )
        batch_op.create_index(
            batch_op.f("ix_processing_task_acquisition_id"), ["acquisition_id"], unique=False
        )


def downgrade() -> None:
    with op.batch_alter_table("processing_task", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_processing_task_acquisition_id"))
        batch_op.drop_index("ix_processing_task_job_state")
    op.drop_table("processing_task")
    with op.batch_alter_table("processing_job", schema=None) as batch_op:
        batch_op.drop_index("ix_processing_job_state")
        batch_op.drop_index("ix_processing_job_created_at")
    op.drop_table("processing_job")
