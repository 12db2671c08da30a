"""Migration 0010 (SQLite and PostgreSQL): the pseudonym key leaves the catalogue for the key
file (or stays only in the environment), refusals change nothing, active tokens get an
expiry, and the downgrade puts the key back."""

from __future__ import annotations

import datetime as dt
import os
from pathlib import Path

import pytest
from sqlalchemy import Engine, inspect, text

from rasterserver.catalog import migrate
from rasterserver.catalog.database import make_engine
from rasterserver.errors import ConflictError, InputError
from rasterserver.pseudonym_key import KEY_ENV, read_key_file, write_key_file

STORED = "5a" * 32


def _at_0009_with_a_key(database_url: str) -> Engine:
    engine = make_engine(database_url)
    migrate.upgrade(engine, "0009")
    now = dt.datetime(2026, 1, 2, 3, 4, 5)
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO pseudonym_key (key_hex, created_at) VALUES (:k, :t)"),
                     {"k": STORED, "t": now})
        conn.execute(text("INSERT INTO pseudonym_key (key_hex, created_at) VALUES (:k, :t)"),
                     {"k": "77" * 32, "t": now})  # a second worker's, never used
        conn.execute(text("INSERT INTO api_account (name, role, kind, created_at) "
                          "VALUES ('dr', 'clinician', 'user', :t)"), {"t": now})
        for digest, revoked in (("a" * 64, None), ("b" * 64, now)):
            conn.execute(text("INSERT INTO api_token (account_id, token_sha256, prefix, label, "
                              "created_at, revoked_at) VALUES (1, :d, 'rs_x', '', :t, :r)"),
                         {"d": digest, "t": now, "r": revoked})
    return engine


def _tables(engine: Engine) -> set[str]:
    return set(inspect(engine).get_table_names())


def test_the_key_moves_to_the_key_file(database_url: str, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv(KEY_ENV, raising=False)
    monkeypatch.delenv("RASTERSERVER_TOKEN_DAYS", raising=False)
    engine = _at_0009_with_a_key(database_url)
    path = tmp_path / "config" / "pseudonym.key"
    before = dt.datetime.now(dt.UTC)
    migrate.upgrade(engine, "0010", key_file=path)
    assert read_key_file(path) == bytes.fromhex(STORED)  # the oldest: the one in use
    assert os.stat(path).st_mode & 0o777 == 0o600
    assert "pseudonym_key" not in _tables(engine)
    with engine.connect() as conn:
        rows = dict(conn.execute(text("SELECT token_sha256, expires_at FROM api_token")).all())
        disabled = conn.execute(text("SELECT disabled_at FROM api_account")).scalar_one()
    assert disabled is None and rows["b" * 64] is None  # a revoked token needs no expiry
    expires = rows["a" * 64]
    expires = expires if isinstance(expires, dt.datetime) else dt.datetime.fromisoformat(expires)
    expires = expires if expires.tzinfo else expires.replace(tzinfo=dt.UTC)
    assert dt.timedelta(days=89) < expires - before < dt.timedelta(days=91)

    # down again: the key goes back into the catalogue, for an older rasterserver
    migrate.downgrade(engine, "0009", key_file=path)
    with engine.connect() as conn:
        assert conn.execute(text("SELECT key_hex FROM pseudonym_key")).scalars().all() == [
            STORED]
    # and up again: the same key is in the file already, nothing to refuse
    migrate.upgrade(engine, key_file=path)
    assert migrate.current_revision(engine) == migrate.head_revision(engine)
    engine.dispose()


def test_refusals_change_nothing(database_url: str, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv(KEY_ENV, raising=False)
    engine = _at_0009_with_a_key(database_url)
    with pytest.raises(InputError, match="rasterserver db upgrade"):
        migrate.upgrade(engine)  # not told where the key file is
    assert migrate.current_revision(engine) == "0009" and "pseudonym_key" in _tables(engine)
    path = tmp_path / "pseudonym.key"
    write_key_file(path, b"o" * 32)
    with pytest.raises(ConflictError, match="different key"):
        migrate.upgrade(engine, key_file=path)
    assert migrate.current_revision(engine) == "0009" and "pseudonym_key" in _tables(engine)
    assert read_key_file(path) == b"o" * 32
    # the environment holds the stored key: nothing written, the table goes
    monkeypatch.setenv(KEY_ENV, STORED)
    other = tmp_path / "unused.key"
    migrate.upgrade(engine, key_file=other)
    assert not other.exists() and "pseudonym_key" not in _tables(engine)
    engine.dispose()


def test_a_catalogue_without_a_key_needs_no_key_file(database_url: str) -> None:
    engine = make_engine(database_url)
    migrate.upgrade(engine)  # a new catalogue: no key file involved at all
    assert "pseudonym_key" not in _tables(engine)
    engine.dispose()
