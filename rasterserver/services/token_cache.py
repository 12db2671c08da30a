"""The owners of API tokens, kept in memory on PostgreSQL and dropped when the database says so.

Every request authenticates its bearer token (:func:`rasterserver.services.auth.authenticate`).
On PostgreSQL that look-up is a network round trip, and under load it cost about a tenth of
the CPU time of a request, on the server and in the database. A plain cache would let a
revoked token keep working until the entry expired, which the API does not allow.

So the cache is only as old as the database's last word. Migration 0006 makes every
statement that changes ``api_token`` or ``api_account`` (also one typed by hand in psql)
send ``NOTIFY rasterserver_auth``. Each server process keeps one connection of its own
listening on that channel, in a thread; any notification empties the cache. A revocation
therefore takes effect as soon as its notification arrives, milliseconds after the commit.

The cache is used only while that connection is listening. When it breaks, the cache is
emptied and bypassed (every request reads the database, as without a cache) until the
thread has reconnected and listens again; then it is emptied once more, since
notifications sent in between were lost. A time-to-live bounds what a silently dead
connection could keep (defence in depth: TCP keep-alives should notice such a connection
first).

On SQLite there is no cache: the look-up runs in the process (tens of microseconds) and
there is nobody to send notifications. :func:`token_cache_for` returns None there.
"""

from __future__ import annotations

import contextlib
import logging
import selectors
import socket
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from sqlalchemy import Engine

if TYPE_CHECKING:
    import psycopg

    from rasterserver.services.auth import Principal

log = logging.getLogger(__name__)

#: The channel the triggers of migration 0006 notify.
CHANNEL = "rasterserver_auth"

# How the listener connects: give up a connection attempt after a few seconds, and let the
# kernel probe an idle connection, so that a peer that vanished without closing it (a
# network cut) is noticed in about half a minute rather than after hours.
_CONNECT_OPTIONS: dict[str, Any] = {
    "autocommit": True,
    "connect_timeout": 5,
    "keepalives": 1,
    "keepalives_idle": 10,
    "keepalives_interval": 5,
    "keepalives_count": 3,
    "application_name": "rasterserver token cache",
}


class TokenCache:
    """Token digest → :class:`~rasterserver.services.auth.Principal`, invalidated by NOTIFY.

    Only tokens that were found are kept: a miss is never cached, so a token created a
    moment ago works at once, and forged tokens cannot fill the cache. A thread listens on
    :data:`CHANNEL` on a connection of its own and empties the cache on every notification.

    Parameters
    ----------
    conninfo : str
        libpq connection string of the catalogue (see :func:`token_cache_for`).
    max_entries : int, optional
        At most this many tokens are kept; the oldest is dropped to make room.
    ttl_s : float, optional
        An entry is used for at most this long after it was read (defence in depth).
    min_backoff_s, max_backoff_s : float, optional
        First and longest wait before reconnecting the listener; doubled after each failure.
    connect : callable, optional
        Opens the listener's connection, ``connect(conninfo, **options)``; by default
        :func:`psycopg.connect`. Tests pass one that fails on demand.

    Notes
    -----
    A read that raced with a change must not be stored: the change's notification may
    arrive after the database answered but before the answer is stored, and would then
    have emptied the cache too early. So a caller takes :attr:`generation` before it reads
    the database and hands it to :meth:`put`, which stores nothing if any notification (or
    reconnection) came in between.
    """

    def __init__(
        self,
        conninfo: str,
        *,
        max_entries: int = 10_000,
        ttl_s: float = 60.0,
        min_backoff_s: float = 0.05,
        max_backoff_s: float = 5.0,
        connect: Callable[..., psycopg.Connection[Any]] | None = None,
    ) -> None:
        if connect is None:
            import psycopg

            connect = psycopg.connect
        self._conninfo = conninfo
        self._connect = connect
        self._max_entries = max_entries
        self._ttl_s = ttl_s
        self._min_backoff_s = min_backoff_s
        self._max_backoff_s = max_backoff_s
        # digest -> (principal, monotonic time after which it is not used)
        self._entries: dict[str, tuple[Principal, float]] = {}
        # Held by whatever empties the cache and by put(), so that "the generation is still
        # the one of the read" and "store" happen as one step. get() needs no lock.
        self._lock = threading.Lock()
        self._generation = 0
        self._listening = False
        self._backend_pid: int | None = None
        self._stop = threading.Event()
        # close() writes to one end to wake the listener out of select() at once.
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._thread = threading.Thread(target=self._run, name="token-cache", daemon=True)
        self._thread.start()

    # --- what authenticate() calls -------------------------------------------------

    @property
    def generation(self) -> int:
        """A number that changes whenever the cache is emptied; take it before a read."""
        return self._generation

    @property
    def listening(self) -> bool:
        """Whether the listener is connected and listening, i.e. the cache is in use."""
        return self._listening

    @property
    def backend_pid(self) -> int | None:
        """Process id of the listener's PostgreSQL backend while it is connected."""
        return self._backend_pid

    def get(self, digest: str) -> Principal | None:
        """Return the cached owner of the token with this SHA-256 ``digest``, or None.

        None means "ask the database": not cached, expired, or the listener is down.
        """
        if not self._listening:
            return None
        entry = self._entries.get(digest)
        if entry is None:
            return None
        principal, expires = entry
        if time.monotonic() >= expires:
            self._entries.pop(digest, None)
            return None
        return principal

    def put(self, digest: str, principal: Principal, generation: int) -> bool:
        """Remember ``principal`` as the owner of ``digest``, as read at ``generation``.

        Parameters
        ----------
        digest : str
            SHA-256 hex digest of the token.
        principal : Principal
            Its owner, as the database returned it.
        generation : int
            :attr:`generation` taken before the database was read.

        Returns
        -------
        bool
            Whether it was stored: not when the cache was emptied since ``generation`` (the
            read may predate a change) or the listener is down.
        """
        expires = time.monotonic() + self._ttl_s
        with self._lock:
            if generation != self._generation or not self._listening:
                return False
            if len(self._entries) >= self._max_entries and digest not in self._entries:
                # dicts keep insertion order: drop the entry stored first
                self._entries.pop(next(iter(self._entries)))
            self._entries[digest] = (principal, expires)
        return True

    def invalidate(self) -> None:
        """Empty the cache and start a new generation (reads in flight are not stored)."""
        with self._lock:
            self._generation += 1
            self._entries.clear()

    def __len__(self) -> int:
        return len(self._entries)

    def wait_listening(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for the listener to listen; return whether it does.

        The server does not wait: until then it reads every token from the database.
        """
        deadline = time.monotonic() + timeout
        while not self._listening:
            if time.monotonic() >= deadline or self._stop.is_set():
                return False
            time.sleep(0.01)
        return True

    def close(self) -> None:
        """Stop the listener and close its connection; the cache is not used any more.

        Returns within about a second even if a connection attempt is under way (the
        thread is a daemon and finishes that attempt on its own).
        """
        if self._stop.is_set():
            return
        self._stop.set()
        self._disable()
        # a full buffer (OSError) means a wake-up is pending anyway
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        self._thread.join(timeout=1.0)
        self._wake_w.close()
        if not self._thread.is_alive():
            self._wake_r.close()

    # --- the listener thread ---------------------------------------------------------

    def _disable(self) -> None:
        with self._lock:
            self._listening = False
            self._backend_pid = None
            self._generation += 1
            self._entries.clear()

    def _run(self) -> None:
        backoff = self._min_backoff_s
        failures = 0
        while not self._stop.is_set():
            try:
                conn = self._connect(self._conninfo, **_CONNECT_OPTIONS)
            except Exception as exc:  # any failure to connect: retry later, DB reads meanwhile
                # once per outage at warning level, not every few seconds while it lasts
                (log.debug if failures else log.warning)(
                    "token cache: cannot connect the listener (%s); retrying with back-off, "
                    "tokens are read from the database meanwhile", type(exc).__name__)
                failures += 1
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self._max_backoff_s)
                continue
            try:
                with conn:
                    conn.execute(f"LISTEN {CHANNEL}")
                    # Listening from here on: a change committed later will be announced.
                    # What was cached before (nothing, or entries from before an outage)
                    # may be stale, and reads that began before LISTEN may predate a
                    # change, so empty the cache and start a new generation first.
                    with self._lock:
                        self._generation += 1
                        self._entries.clear()
                        self._backend_pid = conn.info.backend_pid
                        self._listening = not self._stop.is_set()
                    if failures:
                        log.info("token cache: listening again")
                    backoff, failures = self._min_backoff_s, 0
                    self._listen(conn)
            except Exception as exc:  # the connection broke: bypass the cache, reconnect
                if not self._stop.is_set():
                    log.warning("token cache: listener connection lost (%s); tokens are "
                                "read from the database until it is back",
                                type(exc).__name__)
                    failures = 1  # say so when it is back
            finally:
                self._disable()
            if not self._stop.is_set():
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self._max_backoff_s)

    def _listen(self, conn: psycopg.Connection[Any]) -> None:
        """Empty the cache on every notification until close() or a connection error."""
        # a selector, not select.select(): a busy server may have file numbers above 1024
        with selectors.DefaultSelector() as selector:
            selector.register(conn.fileno(), selectors.EVENT_READ)
            selector.register(self._wake_r, selectors.EVENT_READ)
            while not self._stop.is_set():
                ready = selector.select()
                if any(key.fileobj is self._wake_r for key, _ in ready):
                    return
                # Reads what arrived without waiting; raises OperationalError once the
                # server has closed the connection (a terminated backend, a restart).
                if list(conn.notifies(timeout=0)):
                    self.invalidate()

def token_cache_for(engine: Engine, **options: Any) -> TokenCache | None:
    """Return a :class:`TokenCache` for the catalogue at ``engine``, or None on SQLite.

    Parameters
    ----------
    engine : sqlalchemy.Engine
        The catalogue's engine; its URL (with the password) is reused by the listener.
    **options
        Passed on to :class:`TokenCache`.

    Returns
    -------
    TokenCache or None
        None when tokens are best read from the database each time: SQLite (an in-process
        look-up of tens of microseconds), or a PostgreSQL driver other than psycopg 3.2+
        (the listener uses psycopg's ``notifies(timeout=...)``).
    """
    if engine.dialect.name != "postgresql" or engine.driver != "psycopg":
        return None
    import psycopg
    from psycopg.conninfo import make_conninfo

    if tuple(int(part) for part in psycopg.__version__.split(".")[:2]) < (3, 2):
        log.warning("token cache off: it needs psycopg 3.2 or newer (found %s)",
                    psycopg.__version__)
        return None
    # The engine's own connection parameters, as SQLAlchemy hands them to psycopg (host,
    # port, user, password, database and the URL's query options), not the URL rendered
    # as a string: libpq and SQLAlchemy quote special characters in URLs differently.
    _, params = engine.dialect.create_connect_args(engine.url)
    params.pop("context", None)  # psycopg's type adapters, not a libpq option
    return TokenCache(make_conninfo("", **params), **options)
