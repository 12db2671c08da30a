"""Running the installed ``rasterserver`` console script in a fresh process, as a user does.

Shared by the end-to-end and malformed-input tests: nothing is imported into the process
beforehand (no record module, no plugin), and what reaches the user is exactly the exit code,
stdout and stderr seen here.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

#: What Python prints before a traceback: never to be seen by a user of the CLI.
TRACEBACK = "Traceback (most recent call last)"


def installed_command() -> str:
    """The ``rasterserver`` script beside the interpreter running the tests, else on PATH."""
    beside = Path(sys.executable).with_name("rasterserver")
    found = str(beside) if beside.is_file() else shutil.which("rasterserver")
    if found is None:
        raise RuntimeError("the rasterserver console script is not installed")
    return found


def sigint_as_from_a_terminal() -> None:
    """``preexec_fn`` giving the child SIGINT at its default, as a terminal starts a command.

    A suite started in the background of a non-interactive shell (``pytest &``) has SIGINT
    ignored, and its children inherit that; a command then rightly keeps it ignored
    (:func:`rasterserver.interrupts.install`), and a test of Ctrl-C would see nothing.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run_installed(
    *args: str,
    archive: Path | None = None,
    database_url: str | None = None,
    timeout: float = 600,
    env: dict[str, str] | None = None,
) -> subprocess.CompletedProcess[str]:
    """Run ``rasterserver [--archive A] [--database-url U] ARGS`` and return what it did.

    The environment's ``RASTERSERVER_*`` settings are dropped so that only the options given
    here decide the archive and catalogue (SQLite inside the archive by default).
    """
    base = [installed_command()]
    if archive is not None:
        base += ["--archive", str(archive)]
    if database_url is not None:
        base += ["--database-url", database_url]
    clean = {k: v for k, v in os.environ.items() if not k.startswith("RASTERSERVER_")}
    return subprocess.run(
        [*base, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        env={**clean, **(env or {})},
    )


def describe(done: subprocess.CompletedProcess[str]) -> str:
    """The command, its exit code and its output, for an assertion message."""
    return (
        f"{' '.join(done.args[1:])}\nexit {done.returncode}\n"
        f"--- stdout\n{done.stdout[-3000:]}\n--- stderr\n{done.stderr[-3000:]}"
    )
