"""security: the pseudonym key leaves the catalogue; tokens expire; accounts can be disabled

``pseudonym_key`` held the researchers' pseudonym key in plain text, so any copy or backup of
the catalogue could re-identify research data. The key now lives in a key file or an
environment secret (:mod:`rasterserver.pseudonym_key`). This revision moves a stored key into
the key file the running rasterserver names (``rasterserver db upgrade`` and
``Archive.create`` pass it as the Alembic attribute ``pseudonym_key_file``), then drops the
table. It refuses, changing nothing, when

* the key file exists and holds another key (which one is in use is for the site to decide);
* it does not know where the key file is (Alembic run by hand without the attribute).

When ``RASTERSERVER_PSEUDONYM_KEY`` holds the stored key already, nothing is written. A
catalogue without a stored key just loses the empty table.

``api_token.expires_at``: a token is refused from that time on. Tokens that were active
before this revision get ``now + RASTERSERVER_TOKEN_DAYS`` (default 90) days: none lives
forever any more, and none stops working the moment the server is upgraded.

``api_account.disabled_at``: a disabled account's tokens are all refused, at once, until it
is enabled again. On PostgreSQL the triggers of 0006 already announce changes of both tables
to the servers' token caches.

Plain ADD/DROP COLUMN on both dialects (SQLite >= 3.35 drops a column in place), no rebuild.
The downgrade puts the key back into the catalogue when it can read the key file, so that an
older rasterserver keeps the same pseudonyms.

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-23 18:00:00.000000
"""

from __future__ import annotations

import datetime as dt
import os
from collections.abc import Sequence
from pathlib import Path

import sqlalchemy as sa
from alembic import context, op

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# frozen here: later changes of the defaults must not change what this revision did
KEY_ENV = "RASTERSERVER_PSEUDONYM_KEY"
TOKEN_DAYS_ENV = "RASTERSERVER_TOKEN_DAYS"
DEFAULT_TOKEN_DAYS = 90

_key_table = sa.table(
    "pseudonym_key",
    sa.column("id", sa.Integer),
    sa.column("key_hex", sa.String),
    sa.column("created_at", sa.DateTime(timezone=True)),
)


def _key_file() -> Path | None:
    path = context.config.attributes.get("pseudonym_key_file")
    return Path(path) if path else None


def _move_key_out(conn: sa.Connection) -> None:
    from rasterserver.errors import ConflictError, InputError
    from rasterserver.pseudonym_key import parse_key, read_key_file, write_key_file

    stored = conn.execute(sa.select(_key_table.c.key_hex).order_by(_key_table.c.id)).first()
    if stored is None:
        return
    key = bytes.fromhex(stored[0])
    env = os.environ.get(KEY_ENV, "")
    if env and parse_key(env, KEY_ENV) == key:
        return  # the secret the site keeps already: nothing to write
    path = _key_file()
    if path is None:
        raise InputError(
            "migration 0010 moves the pseudonym key out of the catalogue into the key file, "
            "but was not told where that is: run `rasterserver db upgrade` (with "
            "RASTERSERVER_PSEUDONYM_KEY_FILE set if the key file is not the default one)"
        )
    existing = read_key_file(path)
    if existing is None:
        write_key_file(path, key)
    elif existing != key:
        raise ConflictError(
            f"migration 0010: the pseudonym key file {path} holds a different key from the "
            "one in the catalogue, and pseudonyms made with the other could no longer be "
            "mapped back. Move that file aside if the catalogue's key is the one in use (it "
            "is, unless RASTERSERVER_PSEUDONYM_KEY was set), then run `rasterserver db "
            "upgrade` again; nothing was changed"
        )


def upgrade() -> None:
    conn = op.get_bind()
    _move_key_out(conn)
    op.drop_table("pseudonym_key")
    op.add_column("api_token", sa.Column("expires_at", sa.DateTime(timezone=True), nullable=True))
    op.add_column(
        "api_account", sa.Column("disabled_at", sa.DateTime(timezone=True), nullable=True)
    )
    days = int(os.environ.get(TOKEN_DAYS_ENV) or DEFAULT_TOKEN_DAYS)
    until = dt.datetime.now(dt.UTC) + dt.timedelta(days=days)
    if conn.dialect.name == "sqlite":
        until = until.replace(tzinfo=None)  # SQLite holds UTC without its zone
    token = sa.table("api_token", sa.column("expires_at", sa.DateTime(timezone=True)),
                     sa.column("revoked_at", sa.DateTime(timezone=True)))
    conn.execute(token.update().where(token.c.revoked_at.is_(None)).values(expires_at=until))


def downgrade() -> None:
    op.drop_column("api_account", "disabled_at")
    op.drop_column("api_token", "expires_at")
    op.create_table(
        "pseudonym_key",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("key_hex", sa.String(length=128), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_pseudonym_key")),
    )
    from rasterserver.pseudonym_key import read_key_file

    path = _key_file()
    key = read_key_file(path) if path is not None else None
    if key is not None:
        now = dt.datetime.now(dt.UTC)
        if op.get_bind().dialect.name == "sqlite":
            now = now.replace(tzinfo=None)
        op.get_bind().execute(_key_table.insert().values(key_hex=key.hex(), created_at=now))
