"""The *runner* of a piece of work: which process on which host does it, and is it still there.

Work that outlives a request (a pipeline run, an HTTP processing job) is marked ``running`` in
the catalogue before it starts. If its process is killed (OOM killer, ``kill -9``, power cut)
nothing marks it finished, so the row also names its runner and a reader asks
:func:`runner_gone` whether that process still exists.

A runner is written as ``host:pid`` followed, where the system tells, by
``@boot/start/pidns``: the kernel's boot id, the process's start time in clock ticks since
boot and its pid namespace (Linux ``/proc``). A pid alone is not enough: after the runner
died the kernel may give its pid to an unrelated process, which would keep the work
"running" for ever, and after a reboot the same pid comes round again early. The start time
tells the two processes apart, the boot id tells the boots apart. The namespace keeps a
process in another container that shares the host name (``network_mode: host``) from being
taken for gone: its pids mean nothing here.

Only runners on this host can be checked. A runner on another host, or one written without a
pid, is never reported gone: not being able to tell must not look like a crash.

Reaping
-------
:func:`reap_runs` stores a pipeline run left ``running`` by a gone process as ``failed``, with
an error beginning :data:`INTERRUPTED`. :class:`rasterserver.pipeline.Pipeline` calls it
whenever runs are listed, an acquisition is planned or the unprocessed ones are selected.
"""

from __future__ import annotations

import datetime as dt
import logging
import os
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

if TYPE_CHECKING:
    from sqlalchemy.engine import CursorResult
    from sqlalchemy.orm import Session

__all__ = [
    "INTERRUPTED",
    "ReapReport",
    "current_runner",
    "describe_runner",
    "local_host",
    "reap_runs",
    "runner_gone",
    "runner_host",
]

log = logging.getLogger(__name__)

#: How the error of a run whose process was killed begins (its status is ``failed``).
INTERRUPTED = "interrupted: "

_PROC = Path("/proc")
_BOOT_ID = _PROC / "sys/kernel/random/boot_id"
_PID_NAMESPACE = _PROC / "self/ns/pid"

#: (pid, runner) of this process, so a forked child computes its own
_current: tuple[int, str] | None = None


def local_host() -> str:
    """The name this host writes into runners (:func:`socket.gethostname`)."""
    return socket.gethostname()


def _boot_id() -> str:
    try:
        return _BOOT_ID.read_text().strip()
    except OSError:
        return ""


def _pid_namespace() -> str:
    try:
        link = os.readlink(_PID_NAMESPACE)  # "pid:[4026531836]"
    except OSError:
        return ""
    return "".join(c for c in link if c.isdigit())


def _stat(pid: int) -> tuple[str, str] | None:
    """(state, start time in clock ticks since boot) of ``pid`` from ``/proc``, if readable."""
    try:
        text = (_PROC / str(pid) / "stat").read_text()
    except OSError:
        return None
    # the command name (field 2) is in parentheses and may itself hold spaces or ')'
    fields = text[text.rfind(")") + 2 :].split()
    if len(fields) < 20:
        return None
    return fields[0], fields[19]  # fields 3 and 22 of proc_pid_stat(5)


def _start_token(pid: int) -> str:
    boot = _boot_id()
    stat = _stat(pid)
    if not boot or stat is None:
        return ""
    return f"{boot}/{stat[1]}/{_pid_namespace()}"


def current_runner() -> str:
    """The runner of the calling process: ``host:pid@boot/start/pidns`` (``host:pid``
    without ``/proc``).

    Returns
    -------
    str
        Within the 300 characters of the ``runner`` columns (Linux host names have at most
        64).
    """
    global _current
    pid = os.getpid()
    if _current is None or _current[0] != pid:
        token = _start_token(pid)
        runner = f"{local_host()}:{pid}"
        _current = (pid, f"{runner}@{token}" if token else runner)
    return _current[1]


def _parse(runner: str) -> tuple[str, int, str] | None:
    """(host, pid, start token) of ``runner``; None if it names no process."""
    head, sep, token = runner.rpartition("@")
    if not sep:
        head, token = runner, ""
    host, _, pid = head.rpartition(":")
    if not host or not pid.isdigit() or int(pid) <= 0:
        return None
    return host, int(pid), token


def runner_host(runner: str) -> str:
    """The host named by ``runner`` (empty if it names none)."""
    parsed = _parse(runner)
    return parsed[0] if parsed else ""


def describe_runner(runner: str) -> str:
    """``host:pid`` of ``runner``, for messages (the start token means nothing to a reader)."""
    parsed = _parse(runner)
    return f"{parsed[0]}:{parsed[1]}" if parsed else (runner or "unknown process")


def runner_gone(runner: str) -> bool:
    """Whether the process ``runner`` is known to be gone.

    True only when it certainly is: the runner is on this host and its pid is not alive, is
    a zombie, or now belongs to a process started at another time or in an earlier boot than
    the one recorded. A runner on another host or in another pid namespace (container), an
    empty or unparsable runner, or a pid this user may not signal (it exists) gives False.

    Parameters
    ----------
    runner : str
        ``host:pid`` or ``host:pid@boot/start/pidns``, as written by :func:`current_runner`.

    Returns
    -------
    bool
    """
    parsed = _parse(runner)
    if parsed is None:
        return False
    host, pid, token = parsed
    if host != local_host():
        return False
    boot, _, rest = token.partition("/")
    start, _, namespace = rest.partition("/")
    current_boot = _boot_id() if boot else ""
    if boot and current_boot and boot != current_boot:
        return True  # the machine has restarted since: every process of that boot is gone
    if namespace and namespace != _pid_namespace():
        return False  # another container's pid: nothing to look up here
    try:
        os.kill(pid, 0)  # signal 0: only checks that the pid exists
    except ProcessLookupError:
        return True
    except PermissionError:
        pass  # it exists, as another user's process: its start time still tells
    stat = _stat(pid)
    if stat is None:
        return False  # no /proc here: the pid exists and that is all we know
    state, started = stat
    if state in ("Z", "X"):
        return True  # dead, not yet reaped by its parent
    return bool(start) and bool(current_boot) and started != start


# --- reaping pipeline runs ---------------------------------------------------------------------


@dataclass
class ReapReport:
    """What :func:`reap_runs` found among the ``running`` runs.

    Attributes
    ----------
    marked : int
        Runs marked interrupted (with ``dry_run``: that would have been).
    alive : int
        Runs of live processes on this host, left running.
    unchecked : dict of str to int
        Per host, runs left running that cannot be checked from here: those of other hosts
        not named in ``hosts``, and those recorded before runs named their process.
    """

    marked: int = 0
    alive: int = 0
    unchecked: dict[str, int] = field(default_factory=dict)


def _interruption(host: str, runner: str, declared: frozenset[str]) -> str | None:
    """The error to store for a ``running`` run, or None to leave it running."""
    if runner_gone(runner):
        return f"{INTERRUPTED}the process running it ({describe_runner(runner)}) is gone"
    where = runner_host(runner) or host
    if where not in declared:
        return None
    if where == local_host() and runner_host(runner):
        return None  # its process is here and alive: naming the host does not stop it
    return (
        f"{INTERRUPTED}host {where} was reported to run it no longer "
        f"(`rasterserver runs reap --host {where}`); it ran as {describe_runner(runner)}"
    )


def reap_runs(
    s: Session,
    report: ReapReport | None = None,
    *,
    acquisition_id: int | None = None,
    local_only: bool = False,
    declared: frozenset[str] = frozenset(),
    dry_run: bool = False,
) -> ReapReport:
    """Mark the pipeline runs left ``running`` by gone processes as interrupted, in ``s``.

    Parameters
    ----------
    s : sqlalchemy.orm.Session
        The session to read and update in (its transaction commits the marks).
    report : ReapReport, optional
        Added to; a new one by default.
    acquisition_id : int, optional
        Only this acquisition's runs.
    local_only : bool, optional
        Only runs of this host (the automatic path: other hosts cannot be checked anyway).
    declared : frozenset of str, optional
        Hosts whose ``running`` runs are to be taken as stopped.
    dry_run : bool, optional
        Count, change nothing.

    Returns
    -------
    ReapReport
    """
    # imported here: this module is also read by light modules that need no database
    from sqlalchemy import select, update

    from rasterserver.catalog.models import PipelineRun

    report = report if report is not None else ReapReport()
    query = select(PipelineRun.id, PipelineRun.host, PipelineRun.runner).where(
        PipelineRun.status == "running"
    )
    if acquisition_id is not None:
        query = query.where(PipelineRun.acquisition_id == acquisition_id)
    here = local_host()
    if local_only:
        query = query.where(PipelineRun.host == here)
    for run_id, host, runner in s.execute(query).all():
        error = _interruption(host, runner, declared)
        if error is None:
            where = runner_host(runner) or host
            if where == here and runner:
                report.alive += 1
            else:
                report.unchecked[where] = report.unchecked.get(where, 0) + 1
            continue
        if dry_run:
            report.marked += 1
            continue
        # only if still running: its process may have finished it since it was read
        # Session.execute is typed Result; an UPDATE gives a CursorResult (its rowcount)
        done = cast("CursorResult[Any]", s.execute(
            update(PipelineRun)
            .where(PipelineRun.id == run_id, PipelineRun.status == "running")
            .values(status="failed", finished_at=dt.datetime.now(dt.UTC), error=error)
            .execution_options(synchronize_session=False)
        ))
        if done.rowcount:
            report.marked += 1
            log.warning("pipeline run %d marked failed: %s", run_id, error)
    return report
