"""Runners: which process does a piece of work, and whether it is known to be gone."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import pytest

from rasterserver.runner import (
    current_runner,
    describe_runner,
    local_host,
    runner_gone,
    runner_host,
)

HOST = local_host()
needs_proc = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="no /proc")


def _dead_pid() -> int:
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


def test_this_process_is_its_own_live_runner() -> None:
    runner = current_runner()
    assert runner.startswith(f"{HOST}:{os.getpid()}")
    assert runner_host(runner) == HOST
    assert describe_runner(runner) == f"{HOST}:{os.getpid()}"
    assert not runner_gone(runner)
    assert not runner_gone(f"{HOST}:{os.getpid()}")  # as api_job rows before start times


def test_a_finished_process_is_gone() -> None:
    pid = _dead_pid()
    assert runner_gone(f"{HOST}:{pid}")
    assert runner_gone(f"{HOST}:{pid}@{current_runner().partition('@')[2]}")


@needs_proc
def test_a_zombie_is_gone() -> None:
    child = subprocess.Popen(["true"])
    try:
        stat = Path(f"/proc/{child.pid}/stat")
        deadline = time.monotonic() + 10
        while ") Z " not in stat.read_text() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert runner_gone(f"{HOST}:{child.pid}")  # exists, but dead and not yet reaped
    finally:
        child.wait()


@needs_proc
def test_a_pid_now_used_by_another_process_or_boot_is_gone() -> None:
    boot, start, namespace = current_runner().partition("@")[2].split("/")
    assert boot and start.isdigit() and namespace.isdigit()
    pid = os.getpid()  # alive, but not the process that was recorded
    assert runner_gone(f"{HOST}:{pid}@{boot}/{int(start) + 1}/{namespace}")
    assert runner_gone(f"{HOST}:{pid}@00000000-0000-0000-0000-000000000000/{start}/{namespace}")
    assert not runner_gone(f"{HOST}:{pid}@{boot}/{start}/{namespace}")
    assert not runner_gone(f"{HOST}:{pid}@{boot}/{start}")  # namespace unknown: same pid space


@needs_proc
def test_a_process_of_another_pid_namespace_is_not_judged_from_here() -> None:
    """A container sharing the host name: its pids are not ours to look up."""
    boot, start, namespace = current_runner().partition("@")[2].split("/")
    other = int(namespace) + 1
    assert not runner_gone(f"{HOST}:{_dead_pid()}@{boot}/{start}/{other}")
    assert not runner_gone(f"{HOST}:{os.getpid()}@{boot}/{int(start) + 1}/{other}")
    # but a restart of the machine ended every container's processes too
    assert runner_gone(f"{HOST}:{os.getpid()}@not-this-boot/{start}/{other}")


@pytest.mark.parametrize(
    "runner",
    ["", "no-pid", f"{HOST}:", f"{HOST}:0", f"{HOST}:-1", f"{HOST}:abc",
     "elsewhere.invalid:1", "elsewhere.invalid:999999999@boot/1"],
)
def test_what_cannot_be_checked_here_is_never_gone(runner: str) -> None:
    assert not runner_gone(runner)


def test_runner_parts_for_messages() -> None:
    assert runner_host("h.example:12@b/3") == "h.example"
    assert describe_runner("h.example:12@b/3") == "h.example:12"
    assert runner_host("") == "" and describe_runner("") == "unknown process"
