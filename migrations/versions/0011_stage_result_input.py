"""results computed from several acquisitions: stage_result_input

A comparison of two visits is a stage result (``stage_result`` row, stored under visit A's
acquisition) whose input is not one parent result but several, from two acquisitions. Each
input is a row here: the result it was computed from (the mesh and the analysis of each
visit), its position, and the acquisition it belongs to. The foreign keys RESTRICT deletes:
a result that a stored comparison was computed from cannot be removed from under it.

Revision ID: 0011
Revises: 0010
Create Date: 2026-11-23 18:40:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0011"
down_revision: str | None = "0010"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "stage_result_input",
        sa.Column("result_id", sa.Integer(), nullable=False),
        sa.Column("position", sa.Integer(), nullable=False),
        sa.Column("role", sa.String(length=32), nullable=False),
        sa.Column("input_id", sa.Integer(), nullable=False),
        sa.Column("acquisition_id", sa.Integer(), nullable=False),
        sa.ForeignKeyConstraint(
            ["result_id"],
            ["stage_result.id"],
            name=op.f("fk_stage_result_input_result_id_stage_result"),
            ondelete="RESTRICT",
        ),
        sa.ForeignKeyConstraint(
            ["input_id"],
            ["stage_result.id"],
            name=op.f("fk_stage_result_input_input_id_stage_result"),
            ondelete="RESTRICT",
        ),
        sa.ForeignKeyConstraint(
            ["acquisition_id"],
            ["acquisition.id"],
            name=op.f("fk_stage_result_input_acquisition_id_acquisition"),
            ondelete="RESTRICT",
        ),
        sa.PrimaryKeyConstraint("result_id", "position", name=op.f("pk_stage_result_input")),
    )
    with op.batch_alter_table("stage_result_input", schema=None) as batch_op:
        batch_op.create_index("ix_stage_result_input_input", ["input_id"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("stage_result_input", schema=None) as batch_op:
        batch_op.drop_index("ix_stage_result_input_input")
    op.drop_table("stage_result_input")
