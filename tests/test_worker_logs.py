"""The local cluster's workers: the teardown race's heartbeat error stays off the terminal,
a heartbeat that fails while the worker runs does not."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import pytest

from rasterserver.worker_logs import CLOSING_HEARTBEAT, QuietClosingHeartbeat


def _record(message: str) -> logging.LogRecord:
    return logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1, message, (), None)


@pytest.mark.parametrize(
    ("status", "message", "shown"),
    [
        ("Status.closing", CLOSING_HEARTBEAT + ".", False),
        ("Status.closed", CLOSING_HEARTBEAT + ".", False),
        ("Status.running", CLOSING_HEARTBEAT + ".", True),
        ("Status.closing", "Compute Failed", True),
    ],
)
def test_only_the_closing_heartbeat_is_filtered(status: str, message: str, shown: bool) -> None:
    from distributed.core import Status

    worker = SimpleNamespace(status=getattr(Status, status.split(".")[1]))
    logger = logging.getLogger("distributed.worker")
    before = list(logger.filters)
    try:
        QuietClosingHeartbeat().setup(worker)
        assert bool(logger.filters[-1].filter(_record(message))) is shown
    finally:
        logger.filters[:] = before
