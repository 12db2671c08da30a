"""Group commit of the audit trail: many requests' rows, one transaction, one fsync.

Every audited request must have its rows committed before its response starts. Committed
one request at a time, the catalogue's durable commit (an fsync, ~4 ms here) is the ceiling
of the whole server: SQLite admits one writer, so at most ~250 audited requests per second
whatever the number of workers, and under 50 concurrent clients the queue for that lock was
the tail latency. One writer thread per process instead takes every request that is waiting
and commits all their rows together: the guarantee is the same (no response before its own
rows are durable), the fsync is shared.

A batch that fails is retried request by request, so one request's bad rows cannot cost the
others their answer.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any

log = logging.getLogger(__name__)

Rows = Sequence[dict[str, Any]]
# inserts rows in one transaction and commits; raises when they are not stored
Insert = Callable[[Rows], None]

# Bounds one transaction; a list request brings up to one row per patient on its page.
MAX_BATCH_ROWS = 20_000


class AuditWriter:
    """A thread that commits queued audit rows in batches.

    Parameters
    ----------
    insert : callable
        ``insert(rows)`` stores the rows in one committed transaction or raises.
    max_batch_rows : int
        Most rows in one transaction (a single larger request is still written whole).
    """

    def __init__(self, insert: Insert, *, max_batch_rows: int = MAX_BATCH_ROWS) -> None:
        self._insert = insert
        self._max_rows = max_batch_rows
        self._queue: queue.SimpleQueue[tuple[Rows, Future[None]] | None] = queue.SimpleQueue()
        self._closed = False
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="audit-writer", daemon=True)
        self._thread.start()

    def submit(self, rows: Rows) -> Future[None]:
        """Queue one request's rows; the future is done once they are committed.

        Raises
        ------
        RuntimeError
            The writer is closed.
        """
        future: Future[None] = Future()
        with self._lock:
            if self._closed:
                raise RuntimeError("the audit writer is closed")
            self._queue.put((rows, future))
        return future

    def write(self, rows: Rows) -> None:
        """Queue ``rows`` and wait until they are committed (or raise why not)."""
        self.submit(rows).result()

    def close(self) -> None:
        """Commit what is queued, then stop the thread."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._queue.put(None)
        self._thread.join()

    def _run(self) -> None:
        stopping = False
        while not stopping:
            item = self._queue.get()
            if item is None:
                break
            batch = [item]
            size = len(item[0])
            # Everything that queued while the last batch was being committed goes in this one.
            while size < self._max_rows:
                try:
                    more = self._queue.get_nowait()
                except queue.Empty:
                    break
                if more is None:
                    stopping = True
                    break
                batch.append(more)
                size += len(more[0])
            self._commit(batch)

    def _commit(self, batch: list[tuple[Rows, Future[None]]]) -> None:
        live = [(rows, f) for rows, f in batch if f.set_running_or_notify_cancel()]
        if not live:
            return
        try:
            self._insert([row for rows, _ in live for row in rows])
        except Exception as exc:
            if len(live) == 1:
                live[0][1].set_exception(exc)
            else:
                # one request's rows, or the database, failed: settle each request alone
                self._one_by_one(live)
            return
        for _, future in live:
            future.set_result(None)

    def _one_by_one(self, live: list[tuple[Rows, Future[None]]]) -> None:
        for rows, future in live:
            try:
                self._insert(rows)
            except Exception as exc:  # handed to the waiting request, which answers 503
                future.set_exception(exc)
            else:
                future.set_result(None)
