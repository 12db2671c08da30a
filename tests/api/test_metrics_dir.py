"""The metrics directories of ``serve --workers N``: those of servers that are gone go."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

from rasterserver.api.metrics_dir import OWNER, PREFIX, make_metrics_dir, remove_stale_metrics_dirs
from rasterserver.runner import current_runner, local_host


def _dead_pid() -> int:
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


def test_only_the_directories_of_gone_servers_are_removed(tmp_path: Path) -> None:
    def made(name: str, owner: str | None = None, files: tuple[str, ...] = ()) -> Path:
        directory = tmp_path / (PREFIX + name)
        directory.mkdir()
        if owner is not None:
            (directory / OWNER).write_text(owner + "\n")
        for f in files:
            (directory / f).write_bytes(b"\0" * 16)
        return directory

    dead = _dead_pid()
    killed = made("killed", f"{local_host()}:{dead}", ("counter_9.db",))
    running = made("running", current_runner(), (f"counter_{os.getpid()}.db",))
    elsewhere = made("elsewhere", f"another-host:{dead}")
    old_dead = made("old-dead", files=(f"counter_{dead}.db", f"histogram_{dead}.db"))
    old_alive = made("old-alive", files=(f"counter_{dead}.db", f"counter_{os.getpid()}.db"))
    old_empty = made("old-empty")
    os.utime(old_empty, (time.time() - 7200, time.time() - 7200))
    young_empty = made("young-empty")
    other = tmp_path / "unrelated"
    other.mkdir()

    removed = remove_stale_metrics_dirs(tmp_path)
    assert sorted(removed) == sorted([killed, old_dead, old_empty])
    for kept in (running, elsewhere, old_alive, young_empty, other):
        assert kept.is_dir()
    assert remove_stale_metrics_dirs(tmp_path) == []


def test_a_new_directory_names_its_owner(tmp_path: Path) -> None:
    directory = make_metrics_dir(tmp_path)
    assert directory.parent == tmp_path and directory.name.startswith(PREFIX)
    assert (directory / OWNER).read_text().strip() == current_runner()
    assert [p.name for p in directory.iterdir()] == [OWNER]
    assert oct(directory.stat().st_mode & 0o777) == oct(0o700)
    assert remove_stale_metrics_dirs(tmp_path) == []
