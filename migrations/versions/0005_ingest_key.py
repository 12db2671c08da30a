"""idempotent ingest: ingest_key (source, key) -> acquisition

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-22 05:50:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "ingest_key",
        sa.Column("source", sa.String(length=100), nullable=False),
        sa.Column("key", sa.String(length=100), nullable=False),
        sa.Column("acquisition_id", sa.Integer(), nullable=False),
        sa.Column("request_sha256", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["acquisition_id"], ["acquisition.id"],
            name=op.f("fk_ingest_key_acquisition_id_acquisition"), ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("source", "key", name=op.f("pk_ingest_key")),
    )


def downgrade() -> None:
    op.drop_table("ingest_key")
