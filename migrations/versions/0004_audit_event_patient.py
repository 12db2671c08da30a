"""audit trail: one event per request, the patients it touched in audit_event_patient

Before, a request that listed a hundred patients' acquisitions wrote a hundred full audit
rows; now it writes one event and a hundred (patient, event) links. The patients of the
events already recorded are copied into the new table, so every query reads the links only;
their ``audit_event.patient_id`` stays (the table is append-only) but nothing reads it.

The links have no foreign keys, on purpose: see AuditEventPatient.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-22 04:50:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# append-only like audit_event (migration 0003)
_SQLITE_TRIGGERS = (
    "CREATE TRIGGER audit_event_patient_no_update BEFORE UPDATE ON audit_event_patient "
    "BEGIN SELECT RAISE(ABORT, 'audit events are append-only'); END",
    "CREATE TRIGGER audit_event_patient_no_delete BEFORE DELETE ON audit_event_patient "
    "BEGIN SELECT RAISE(ABORT, 'audit events are append-only'); END",
)
# the function audit_event_append_only() of migration 0003 serves this table too
_PG_TRIGGERS = (
    "CREATE TRIGGER audit_event_patient_append_only BEFORE UPDATE OR DELETE "
    "ON audit_event_patient FOR EACH ROW EXECUTE FUNCTION audit_event_append_only()",
)


def upgrade() -> None:
    op.create_table(
        "audit_event_patient",
        sa.Column("patient_id", sa.Integer(), nullable=False),
        sa.Column("event_id", sa.Integer(), nullable=False),
        sa.PrimaryKeyConstraint("patient_id", "event_id", name=op.f("pk_audit_event_patient")),
        sqlite_with_rowid=False,
    )
    op.create_index("ix_audit_event_patient_event_id", "audit_event_patient", ["event_id"])
    op.execute(
        "INSERT INTO audit_event_patient (patient_id, event_id) "
        "SELECT patient_id, id FROM audit_event WHERE patient_id IS NOT NULL"
    )
    # every query now finds patients through the links
    op.drop_index("ix_audit_event_patient_recorded", table_name="audit_event")
    dialect = op.get_bind().dialect.name
    for statement in {"sqlite": _SQLITE_TRIGGERS, "postgresql": _PG_TRIGGERS}.get(dialect, ()):
        op.execute(statement)


def downgrade() -> None:
    # Events recorded since the upgrade name their patients only in the links; dropping
    # them would erase from the audit trail whose data those requests touched.
    newer = op.get_bind().execute(sa.text(
        "SELECT count(*) FROM audit_event_patient l JOIN audit_event e ON e.id = l.event_id "
        "WHERE e.patient_id IS NULL")).scalar()
    if newer:
        raise RuntimeError(
            f"{newer} audit links were recorded since migration 0004; downgrading would lose "
            "which patients those requests touched. Export the audit trail first "
            "(`rasterserver audit export`) and remove this check knowingly if you must.")
    dialect = op.get_bind().dialect.name
    if dialect == "postgresql":
        op.execute("DROP TRIGGER IF EXISTS audit_event_patient_append_only "
                   "ON audit_event_patient")
    elif dialect == "sqlite":
        op.execute("DROP TRIGGER IF EXISTS audit_event_patient_no_update")
        op.execute("DROP TRIGGER IF EXISTS audit_event_patient_no_delete")
    op.create_index("ix_audit_event_patient_recorded", "audit_event",
                    ["patient_id", "recorded_at"])
    op.drop_index("ix_audit_event_patient_event_id", table_name="audit_event_patient")
    op.drop_table("audit_event_patient")
