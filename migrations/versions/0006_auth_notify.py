"""auth notify: any change to api_token or api_account sends NOTIFY rasterserver_auth

On PostgreSQL the API server keeps the owners of the tokens it has seen in memory
(rasterserver.api.token_cache), to spare every request a round trip to the database. A
revoked token must still be refused from the next request on, so the database itself
announces every change to the two tables the look-up reads, and the servers listening on
the channel drop what they hold. The triggers fire on any statement, not only those of
rasterserver: a revocation typed by hand in psql invalidates the caches just the same.

Statement-level triggers, not row-level: one notification per statement is enough (the
listeners clear everything), TRUNCATE has no rows, and PostgreSQL folds identical
notifications of one transaction into one, delivered at commit.

SQLite: nothing to do; the server does not cache there (the look-up is in-process).

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-22 06:40:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# the channel rasterserver.api.token_cache listens on
CHANNEL = "rasterserver_auth"
_TABLES = ("api_token", "api_account")

_PG_FUNCTION = (
    "CREATE FUNCTION rasterserver_auth_changed() RETURNS trigger AS $$ "
    f"BEGIN PERFORM pg_notify('{CHANNEL}', ''); RETURN NULL; END; $$ LANGUAGE plpgsql"
)


def upgrade() -> None:
    if op.get_bind().dialect.name != "postgresql":
        return
    op.execute(_PG_FUNCTION)
    for table in _TABLES:
        op.execute(
            f"CREATE TRIGGER {table}_auth_changed "
            f"AFTER INSERT OR UPDATE OR DELETE OR TRUNCATE ON {table} "
            "FOR EACH STATEMENT EXECUTE FUNCTION rasterserver_auth_changed()"
        )


def downgrade() -> None:
    if op.get_bind().dialect.name != "postgresql":
        return
    for table in _TABLES:
        op.execute(f"DROP TRIGGER IF EXISTS {table}_auth_changed ON {table}")
    op.execute("DROP FUNCTION IF EXISTS rasterserver_auth_changed()")
