"""The token cache on PostgreSQL: served without a query, emptied by NOTIFY, bypassed while
its listener is down; and its absence on SQLite.

Against the real PostgreSQL server of tests/conftest.py (each test in a database of its
own); skipped with the reason when there is none.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import psycopg
import pytest
from api_helpers import LiveServer
from sqlalchemy import event, text

from rasterserver.api.app import ApiSettings, Services
from rasterserver.archive import Archive
from rasterserver.cli import main
from rasterserver.config import Settings, sqlite_url
from rasterserver.services import auth
from rasterserver.services.token_cache import CHANNEL, TokenCache, token_cache_for

pytestmark = pytest.mark.timeout(60)

# how long a notification may take to arrive before a test fails (it takes milliseconds)
DELIVERY_S = 2.0
# how long close() may take (documented: about a second; a 30 s back-off must not count)
CLOSE_S = 1.5


@pytest.fixture
def pg_archive(postgres_url: str, tmp_path: Path) -> Iterator[Archive]:
    """A migrated PostgreSQL archive with one clinician account."""
    root = tmp_path / "archive"
    with Archive.create(Settings(archive=root, database_url=postgres_url)) as archive:
        auth.add_account(archive, "dr-who", role="clinician")
        yield archive


class Gate:
    """Opens the listener's connections while open; makes them fail while closed."""

    def __init__(self) -> None:
        self.open = threading.Event()
        self.open.set()
        self.attempts = 0

    def connect(self, conninfo: str, **options: Any) -> psycopg.Connection[Any]:
        self.attempts += 1
        if not self.open.is_set():
            raise psycopg.OperationalError("refused by the test")
        return psycopg.connect(conninfo, **options)


@pytest.fixture
def gate() -> Gate:
    return Gate()


@pytest.fixture
def cache(pg_archive: Archive, gate: Gate) -> Iterator[TokenCache]:
    """A listening token cache of ``pg_archive`` whose reconnections ``gate`` controls."""
    token_cache = token_cache_for(pg_archive.engine, connect=gate.connect)
    assert isinstance(token_cache, TokenCache)
    try:
        assert token_cache.wait_listening(10)
        yield token_cache
    finally:
        token_cache.close()


@pytest.fixture
def token_reads(pg_archive: Archive) -> Iterator[list[str]]:
    """The token look-ups ``pg_archive`` sends to the database, as they are sent."""
    reads: list[str] = []

    def count(_conn: Any, _cursor: Any, statement: str, *_args: Any) -> None:
        if is_token_read(statement):
            reads.append(statement)

    event.listen(pg_archive.engine, "before_cursor_execute", count)
    yield reads
    event.remove(pg_archive.engine, "before_cursor_execute", count)


def is_token_read(statement: str) -> bool:
    """Whether ``statement`` is authenticate()'s look-up."""
    return statement.startswith("SELECT") and "api_token.token_sha256 =" in statement


def until(condition: Callable[[], bool], timeout: float = DELIVERY_S) -> bool:
    """Poll ``condition`` until it holds or ``timeout`` passes; return whether it held."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def settled_token(archive: Archive, cache: TokenCache) -> str:
    """A new token of dr-who, once the cache has seen the notification its creation sent
    (else that notification could refuse the read a test makes next)."""
    generation = cache.generation
    token = auth.create_token(archive, "dr-who")
    until(lambda: cache.generation != generation, 0.5)
    return token


def token_id(archive: Archive, account: str = "dr-who") -> int:
    return auth.tokens(archive, account=account)[-1].id


def test_a_cached_token_is_served_without_a_query_and_misses_are_not_cached(
    pg_archive: Archive, cache: TokenCache, token_reads: list[str],
) -> None:
    token = settled_token(pg_archive, cache)
    first = auth.authenticate(pg_archive, token, cache)
    assert first == auth.Principal(first.account_id, "dr-who", "clinician", "user")
    assert len(token_reads) == 1 and len(cache) == 1
    for _ in range(3):
        assert auth.authenticate(pg_archive, token, cache) == first
    assert len(token_reads) == 1
    # a forged or unknown token is read every time: nothing to fill the cache with
    for _ in range(2):
        assert auth.authenticate(pg_archive, "rs_unknown", cache) is None
    assert len(token_reads) == 3 and len(cache) == 1
    # no cache given: every call reads (the SQLite path, and callers outside the server)
    auth.authenticate(pg_archive, token)
    assert len(token_reads) == 4


def test_revoke_token_refuses_the_token_once_notified(
    pg_archive: Archive, cache: TokenCache,
) -> None:
    token = auth.create_token(pg_archive, "dr-who")
    assert until(lambda: auth.authenticate(pg_archive, token, cache) is not None
                 and len(cache) == 1)
    auth.revoke_token(pg_archive, token_id(pg_archive))
    assert until(lambda: auth.authenticate(pg_archive, token, cache) is None)
    assert len(cache) == 0
    assert auth.authenticate(pg_archive, token, cache) is None


def test_a_hand_typed_sql_revocation_or_role_change_invalidates(
    pg_archive: Archive, cache: TokenCache,
) -> None:
    token = auth.create_token(pg_archive, "dr-who")
    assert until(lambda: auth.authenticate(pg_archive, token, cache) is not None
                 and len(cache) == 1)
    # an administrator in psql, not rasterserver: the trigger notifies all the same
    with pg_archive.engine.begin() as conn:
        conn.execute(text("UPDATE api_account SET role = 'researcher' WHERE name = 'dr-who'"))
    assert until(lambda: auth.authenticate(pg_archive, token, cache).role == "researcher")
    with pg_archive.engine.begin() as conn:
        conn.execute(text("UPDATE api_token SET revoked_at = now() WHERE id = :id"),
                     {"id": token_id(pg_archive)})
    assert until(lambda: auth.authenticate(pg_archive, token, cache) is None)


def test_a_change_announced_during_the_read_is_not_cached(
    pg_archive: Archive, cache: TokenCache, token_reads: list[str],
) -> None:
    token = settled_token(pg_archive, cache)
    notify = psycopg.connect(cache._conninfo, autocommit=True)
    race = {"on": True}

    def notify_during_read(_conn: Any, _cursor: Any, statement: str, *_args: Any) -> None:
        # the database is being asked; a change lands and is announced before the answer
        # is stored
        if race["on"] and "api_token" in statement:
            race["on"] = False
            before = cache.generation
            notify.execute(f"NOTIFY {CHANNEL}")
            assert until(lambda: cache.generation != before)

    event.listen(pg_archive.engine, "before_cursor_execute", notify_during_read)
    try:
        assert auth.authenticate(pg_archive, token, cache) is not None
        assert len(cache) == 0 and len(token_reads) == 1
        # the next read stores its answer, and the one after is served from the cache
        auth.authenticate(pg_archive, token, cache)
        auth.authenticate(pg_archive, token, cache)
        assert len(cache) == 1 and len(token_reads) == 2
    finally:
        event.remove(pg_archive.engine, "before_cursor_execute", notify_during_read)
        notify.close()
    # the same rule, directly: an answer read at an old generation is dropped
    principal = auth.authenticate(pg_archive, token, cache)
    stale = cache.generation
    cache.invalidate()
    assert not cache.put("0" * 64, principal, stale)
    assert cache.put("0" * 64, principal, cache.generation)


def test_the_cache_is_bounded_and_entries_expire(pg_archive: Archive, gate: Gate) -> None:
    small = token_cache_for(pg_archive.engine, connect=gate.connect, max_entries=3,
                            ttl_s=0.2)
    try:
        assert small.wait_listening(10)
        principal = auth.Principal(1, "dr-who", "clinician", "user")
        for i in range(5):
            assert small.put(f"{i:064x}", principal, small.generation)
        assert len(small) == 3
        assert small.get(f"{0:064x}") is None and small.get(f"{4:064x}") == principal
        assert until(lambda: small.get(f"{4:064x}") is None, 1.0)
    finally:
        small.close()


def test_a_lost_listener_bypasses_the_cache_until_it_listens_again(
    pg_archive: Archive, cache: TokenCache, gate: Gate, token_reads: list[str],
) -> None:
    token = auth.create_token(pg_archive, "dr-who")
    assert until(lambda: auth.authenticate(pg_archive, token, cache) is not None
                 and len(cache) == 1)
    pid = cache.backend_pid
    gate.open.clear()
    with pg_archive.engine.connect() as conn:
        assert conn.execute(text("SELECT pg_terminate_backend(:pid)"), {"pid": pid}).scalar()
    assert until(lambda: not cache.listening)
    assert len(cache) == 0 and cache.backend_pid is None
    # down: every look-up reads the database, and a revocation (which nobody can hear)
    # takes effect at once
    reads = len(token_reads)
    for _ in range(3):
        assert auth.authenticate(pg_archive, token, cache) is not None
    assert len(token_reads) == reads + 3 and len(cache) == 0
    down_generation = cache.generation
    auth.revoke_token(pg_archive, token_id(pg_archive))
    assert auth.authenticate(pg_archive, token, cache) is None
    assert until(lambda: gate.attempts >= 2)  # it keeps trying, with back-off
    # back: listening on a new backend, emptied again, caching again
    gate.open.set()
    assert cache.wait_listening(10)
    assert cache.backend_pid not in (None, pid)
    assert not cache.put("0" * 64, auth.Principal(1, "x", "admin", "user"), down_generation)
    assert auth.authenticate(pg_archive, token, cache) is None
    other = auth.create_token(pg_archive, "dr-who")
    assert until(lambda: auth.authenticate(pg_archive, other, cache) is not None
                 and len(cache) == 1)
    reads = len(token_reads)
    assert auth.authenticate(pg_archive, other, cache) is not None
    assert len(token_reads) == reads


def test_close_is_prompt_listening_or_reconnecting(pg_archive: Archive, gate: Gate) -> None:
    listening = token_cache_for(pg_archive.engine, connect=gate.connect)
    assert listening.wait_listening(10)
    pid = listening.backend_pid
    started = time.monotonic()
    listening.close()
    # the promise is "within about a second" (close() joins for at most 1 s): the thread
    # having ended is the real check; the bound leaves room for a loaded CI machine
    assert time.monotonic() - started < CLOSE_S
    assert not listening._thread.is_alive() and not listening.listening
    assert listening.get("0" * 64) is None
    listening.close()  # twice is harmless
    with pg_archive.engine.connect() as conn:  # its connection is gone
        assert until(lambda: not conn.execute(
            text("SELECT count(*) FROM pg_stat_activity WHERE pid = :pid"),
            {"pid": pid}).scalar())
    # never connected, waiting to retry
    gate.open.clear()
    failing = token_cache_for(pg_archive.engine, connect=gate.connect, min_backoff_s=30)
    assert until(lambda: gate.attempts >= 1)
    assert not failing.wait_listening(0.05)
    started = time.monotonic()
    failing.close()
    assert time.monotonic() - started < CLOSE_S and not failing._thread.is_alive()


def test_sqlite_has_no_cache(tmp_path: Path) -> None:
    root = tmp_path / "archive"
    settings = Settings(archive=root, database_url=sqlite_url(root))
    with Archive.create(settings) as archive:
        assert token_cache_for(archive.engine) is None
    services = Services(settings, ApiSettings(threads=1))
    try:
        assert services.token_cache is None
    finally:
        services.close()


def test_a_running_server_refuses_a_token_revoked_by_the_cli(
    start_server: Callable[..., LiveServer], postgres_url: str, tmp_path: Path,
) -> None:
    live = start_server(Settings(archive=tmp_path / "archive", database_url=postgres_url))
    with live.archive() as archive, archive.engine.connect() as conn:
        # the server's listener is up (it caches from here on)
        assert until(lambda: conn.execute(text(
            "SELECT count(*) FROM pg_stat_activity WHERE application_name = "
            "'rasterserver token cache' AND datname = current_database() "
            "AND query = :listen"), {"listen": f"LISTEN {CHANNEL}"}).scalar() == 1, 10)
        (info,) = auth.tokens(archive, account="clinician-1")
    with live.client("clinician") as c:
        for _ in range(3):  # the first reads the database, the others the cache
            assert c.get("/patients").status_code == 200
        base = ["--archive", str(live.settings.archive),
                "--database-url", live.settings.database_url]
        assert main([*base, "token", "revoke", str(info.id)]) == 0
        # The revocation reaches the server as a notification, milliseconds after the
        # commit; the very next request normally finds it already applied, but the test
        # allows for a loaded machine.
        assert until(lambda: c.get("/patients").status_code == 401)
        assert c.get("/patients").status_code == 401
    with live.client("admin") as a:
        assert a.get("/patients").status_code == 403  # other tokens still work
