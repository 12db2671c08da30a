"""Group commit of the audit trail: many requests' records, one transaction, one fsync.

Every audited request must have its rows committed before its response starts. Committed
one request at a time, the catalogue's durable commit (an fsync, ~4 ms here) is the ceiling
of the whole server: SQLite admits one writer, so at most ~250 audited requests per second
whatever the number of workers, and under 50 concurrent clients the queue for that lock was
the tail latency. One writer thread per process instead takes every request that is waiting
and commits all their rows together: the guarantee is the same (no response before its own
rows are durable), the fsync is shared.

A batch that fails is retried request by request, so one request's bad record cannot cost
the others their answer.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

log = logging.getLogger(__name__)

# inserts the records of several requests in one transaction and commits; raises when
# they are not stored
Insert = Callable[[list[Any]], None]

# Bounds one transaction (a record is one request's event and its patient links).
MAX_BATCH = 1000


class AuditWriter:
    """A thread that commits queued audit rows in batches.

    Parameters
    ----------
    insert : callable
        ``insert(records)`` stores a list of records (each one request's) in one committed
        transaction, or raises.
    max_batch : int
        Most records in one transaction.
    """

    def __init__(self, insert: Insert, *, max_batch: int = MAX_BATCH) -> None:
        self._insert = insert
        self._max_batch = max_batch
        self._queue: queue.SimpleQueue[tuple[Any, Future[None]] | None] = queue.SimpleQueue()
        self._closed = False
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="audit-writer", daemon=True)
        self._thread.start()

    def submit(self, record: Any) -> Future[None]:
        """Queue one request's record; the future is done once it is committed.

        Raises
        ------
        RuntimeError
            The writer is closed.
        """
        future: Future[None] = Future()
        with self._lock:
            if self._closed:
                raise RuntimeError("the audit writer is closed")
            self._queue.put((record, future))
        return future

    def write(self, record: Any) -> None:
        """Queue ``record`` and wait until it is committed (or raise why not)."""
        self.submit(record).result()

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
            # Everything that queued while the last batch was being committed goes in this one.
            while len(batch) < self._max_batch:
                try:
                    more = self._queue.get_nowait()
                except queue.Empty:
                    break
                if more is None:
                    stopping = True
                    break
                batch.append(more)
            self._commit(batch)

    def _commit(self, batch: list[tuple[Any, Future[None]]]) -> None:
        live = [(record, f) for record, f in batch if f.set_running_or_notify_cancel()]
        if not live:
            return
        try:
            self._insert([record for record, _ in live])
        except Exception as exc:
            if len(live) == 1:
                live[0][1].set_exception(exc)
            else:
                # one request's rows, or the database, failed: settle each request alone
                self._one_by_one(live)
            return
        for _, future in live:
            future.set_result(None)

    def _one_by_one(self, live: list[tuple[Any, Future[None]]]) -> None:
        for record, future in live:
            try:
                self._insert([record])
            except Exception as exc:  # handed to the waiting request, which answers 503
                future.set_exception(exc)
            else:
                future.set_result(None)
