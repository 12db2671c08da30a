"""The SQLite catalogue's writer lock: exclusive across threads and processes."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

from rasterserver.catalog.database import WriteLock, make_engine
from rasterserver.config import sqlite_url

_HOLDER = """
import sys, time
from pathlib import Path
from rasterserver.catalog.database import WriteLock, make_engine
lock = WriteLock(make_engine(sys.argv[1]))
with lock():
    Path(sys.argv[2]).write_text("held")
    deadline = time.monotonic() + 30
    while not Path(sys.argv[3]).exists() and time.monotonic() < deadline:
        time.sleep(0.01)
"""


def test_another_process_waits_until_the_holder_lets_go(tmp_path: Path) -> None:
    url = sqlite_url(tmp_path / "archive")
    held, release = tmp_path / "held", tmp_path / "release"
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, url, str(held), str(release)])
    try:
        deadline = time.monotonic() + 30
        while not held.exists():
            assert time.monotonic() < deadline and holder.poll() is None
            time.sleep(0.01)
        lock = WriteLock(make_engine(url))
        got = threading.Event()

        def take() -> None:
            with lock():
                got.set()

        taker = threading.Thread(target=take)
        taker.start()
        assert not got.wait(0.3)  # still held by the other process
        release.touch()
        assert got.wait(30)
        taker.join()
        lock.close()
    finally:
        holder.wait(timeout=30)


def test_threads_of_one_process_take_turns(tmp_path: Path) -> None:
    lock = WriteLock(make_engine(sqlite_url(tmp_path / "archive")))
    inside, most = 0, 0
    guard = threading.Lock()

    def work() -> None:
        nonlocal inside, most
        for _ in range(50):
            with lock():
                with guard:
                    inside += 1
                    most = max(most, inside)
                time.sleep(0.0005)
                with guard:
                    inside -= 1

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    lock.close()
    assert most == 1


def test_postgresql_needs_no_lock(database_url: str) -> None:
    lock = WriteLock(make_engine(database_url))
    if not database_url.startswith("sqlite"):
        with lock(), lock():  # nothing to take on PostgreSQL, which locks rows itself
            pass
    lock.close()
