"""The local Dask cluster's workers share the user's terminal: keep a teardown race's
error out of their log."""

from __future__ import annotations

import logging

from distributed import WorkerPlugin

__all__ = ["CLOSING_HEARTBEAT", "QuietClosingHeartbeat"]

#: What a worker of a closing cluster logs, with a traceback, when its last heartbeat meets
#: its own connections closing (a race inside distributed's teardown, dask/distributed#7105):
#: nothing failed, but on the user's terminal it reads as an error.
CLOSING_HEARTBEAT = "Failed to communicate with scheduler during heartbeat"


class _ClosingHeartbeatFilter(logging.Filter):
    """Drops :data:`CLOSING_HEARTBEAT` while the worker is closing; a heartbeat that fails
    while it runs is still logged."""

    def __init__(self, worker: object) -> None:
        super().__init__()
        self.worker = worker

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.getMessage().startswith(CLOSING_HEARTBEAT):
            return True
        status = str(getattr(self.worker, "status", ""))
        return "clos" not in status  # Status.closing, closing_gracefully, closed


class QuietClosingHeartbeat(WorkerPlugin):
    """Worker plugin of the local cluster: its workers share the user's terminal, so the
    teardown race's error (:data:`CLOSING_HEARTBEAT`) is filtered out of their log."""

    name = "rasterserver-quiet-closing-heartbeat"

    def setup(self, worker: object) -> None:
        """Install the filter on the worker's logger."""
        logging.getLogger("distributed.worker").addFilter(_ClosingHeartbeatFilter(worker))

    def teardown(self, worker: object) -> None:
        """Nothing to undo: the worker process ends."""
