"""audit trail: links keyed by event, a by-patient index filled in sorted batches

``audit_event_patient`` was keyed (patient_id, event_id): every group commit of the audit
writer put its links into hundreds of places of that key, and rewrote as many pages. Keyed
(event_id, patient_id) they are appended. The by-patient look-up moves to
``audit_patient_index``, which the audit indexer fills in large sorted batches;
``audit_index_mark`` says how far it is complete. The existing links are indexed here, so
the mark starts at the newest event.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-22 07:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _sqlite_append_only(table: str) -> tuple[str, ...]:
    return tuple(
        f"CREATE TRIGGER {table}_no_{what} BEFORE {what.upper()} ON {table} "
        "BEGIN SELECT RAISE(ABORT, 'audit events are append-only'); END"
        for what in ("update", "delete")
    )


def _append_only(table: str) -> None:
    dialect = op.get_bind().dialect.name
    if dialect == "sqlite":
        for statement in _sqlite_append_only(table):
            op.execute(statement)
    elif dialect == "postgresql":
        # the function of migration 0003 serves every audit table
        op.execute(f"CREATE TRIGGER {table}_append_only BEFORE UPDATE OR DELETE ON {table} "
                   "FOR EACH ROW EXECUTE FUNCTION audit_event_append_only()")


def _drop_append_only(table: str) -> None:
    dialect = op.get_bind().dialect.name
    if dialect == "sqlite":
        op.execute(f"DROP TRIGGER IF EXISTS {table}_no_update")
        op.execute(f"DROP TRIGGER IF EXISTS {table}_no_delete")
    elif dialect == "postgresql":
        op.execute(f"DROP TRIGGER IF EXISTS {table}_append_only ON {table}")


def _rekey_links(key: tuple[str, str], *, event_index: bool) -> None:
    """Give ``audit_event_patient`` the primary key ``key``, keeping every row."""
    if op.get_bind().dialect.name == "postgresql":
        op.drop_constraint("pk_audit_event_patient", "audit_event_patient", type_="primary")
        op.create_primary_key("pk_audit_event_patient", "audit_event_patient", list(key))
        if event_index:
            op.create_index("ix_audit_event_patient_event_id", "audit_event_patient",
                            ["event_id"])
        else:
            op.drop_index("ix_audit_event_patient_event_id", table_name="audit_event_patient")
        return
    # SQLite cannot change a key in place (and the table has no rowid): copy it over
    _drop_append_only("audit_event_patient")
    op.create_table(
        "audit_event_patient_rekeyed",
        *(sa.Column(name, sa.Integer(), nullable=False) for name in key),
        sa.PrimaryKeyConstraint(*key, name="pk_audit_event_patient"),
        sqlite_with_rowid=False,
    )
    columns = ", ".join(key)
    op.execute(f"INSERT INTO audit_event_patient_rekeyed ({columns}) "
               f"SELECT {columns} FROM audit_event_patient ORDER BY {columns}")
    op.drop_table("audit_event_patient")
    op.rename_table("audit_event_patient_rekeyed", "audit_event_patient")
    if event_index:
        op.create_index("ix_audit_event_patient_event_id", "audit_event_patient",
                        ["event_id"])
    _append_only("audit_event_patient")


def upgrade() -> None:
    _rekey_links(("event_id", "patient_id"), event_index=False)
    op.create_table(
        "audit_patient_index",
        sa.Column("patient_id", sa.Integer(), nullable=False),
        sa.Column("event_id", sa.Integer(), nullable=False),
        sa.PrimaryKeyConstraint("patient_id", "event_id", name=op.f("pk_audit_patient_index")),
        sqlite_with_rowid=False,
    )
    op.execute("INSERT INTO audit_patient_index (patient_id, event_id) "
               "SELECT patient_id, event_id FROM audit_event_patient "
               "ORDER BY patient_id, event_id")
    _append_only("audit_patient_index")
    op.create_table(
        "audit_index_mark",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("indexed_through", sa.Integer(), nullable=False),
        sa.Column("lease_until", sa.DateTime(timezone=True), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_audit_index_mark")),
    )
    op.execute("INSERT INTO audit_index_mark (id, indexed_through) "
               "SELECT 1, COALESCE(MAX(id), 0) FROM audit_event")


def downgrade() -> None:
    # nothing is lost: the index is derived from the links, which stay
    op.drop_table("audit_index_mark")
    _drop_append_only("audit_patient_index")
    op.drop_table("audit_patient_index")
    _rekey_links(("patient_id", "event_id"), event_index=True)
