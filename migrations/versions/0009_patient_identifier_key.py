"""patients are unique ignoring case and look-alike characters: patient.identifier_key

``identifier_key`` holds each identifier's comparison key (Unicode NFKC case fold, as
:func:`rasterserver.identifiers.lookup_key` computes it) under a unique index, so ``p-1``,
``Ｐ-1`` (full-width) or a decomposed ``é`` cannot be registered beside ``P-1`` or a composed
``é``, and a look-up of any of them finds the one patient. The identifier itself is kept as
registered: the researchers' pseudonyms are derived from it, and the site's systems hold it so.

A unique index rather than a unique constraint: SQLite adds a constraint only by rebuilding the
table, and ``patient`` is referenced (ON DELETE RESTRICT) by visits, acquisitions and the audit
trail, which a rebuild inside the migration's transaction cannot drop and recreate under
enforced foreign keys (see 0008).

Patients registered before this revision may already be look-alikes of each other. The oldest
of each group (lowest id) gets the key; the others keep a NULL key and stay reachable by their
exact identifier (look-ups try the exact identifier first), so no row becomes unreadable and
none is renamed. Identifiers that break today's character rules (a ``/``, a newline) are left
as they are for the same reason; the rules apply to new ones.

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-23 09:00:00.000000
"""

from __future__ import annotations

import unicodedata
from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# The key as this revision defines it (frozen here: a later change of the rules in
# rasterserver.identifiers must not change what this migration did).
KEY_MAX = 255


def _key(identifier: str) -> str:
    folded = unicodedata.normalize("NFKC", identifier).casefold()
    return unicodedata.normalize("NFKC", folded)


def upgrade() -> None:
    op.add_column("patient", sa.Column("identifier_key", sa.String(length=KEY_MAX), nullable=True))
    conn = op.get_bind()
    patient = sa.table(
        "patient",
        sa.column("id", sa.Integer),
        sa.column("identifier", sa.String),
        sa.column("identifier_key", sa.String),
    )
    taken: set[str] = set()
    keys = []
    for pid, identifier in conn.execute(
        sa.select(patient.c.id, patient.c.identifier).order_by(patient.c.id)
    ):
        key = _key(identifier)
        if key in taken or len(key) > KEY_MAX:
            continue  # a look-alike of an older patient: NULL, reached by its exact identifier
        taken.add(key)
        keys.append({"pid": pid, "key": key})
    if keys:
        conn.execute(
            patient.update()
            .where(patient.c.id == sa.bindparam("pid"))
            .values(identifier_key=sa.bindparam("key")),
            keys,
        )
    op.create_index("ix_patient_identifier_key", "patient", ["identifier_key"], unique=True)


def downgrade() -> None:
    op.drop_index("ix_patient_identifier_key", table_name="patient")
    # SQLite >= 3.35 drops a column in place (no rebuild, see 0008)
    op.drop_column("patient", "identifier_key")
