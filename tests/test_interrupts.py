"""A Ctrl-C that a finaliser swallowed still stops the command and ends it with exit 130.

Each case runs in a fresh interpreter: a signal handler belongs to the process, and the
test process's own SIGINT handling must stay pytest's.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import pytest

#: A finaliser that receives SIGINT: Python prints "Exception ignored" and goes on.
_SWALLOW = """
import gc, os, signal, time
from rasterserver.interrupts import install, interrupted, raise_if_interrupted

install()

class Finaliser:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000):  # the handler runs at the next bytecode check: in here
            time.sleep(0.001)

Finaliser()
gc.collect()
print("went on", interrupted())
"""


def _sigint_at_default() -> None:
    # as a terminal starts a command: a suite run in the background of a non-interactive
    # shell has SIGINT ignored, the child would inherit it and rightly keep it ignored
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _python(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=_sigint_at_default,
    )


def test_swallowed_interrupt_is_remembered_and_raised_again() -> None:
    done = _python(
        _SWALLOW
        + """
try:
    raise_if_interrupted()
except KeyboardInterrupt:
    print("raised again")
"""
    )
    assert "Exception ignored" in done.stderr and "KeyboardInterrupt" in done.stderr, done
    assert done.stdout.splitlines() == ["went on True", "raised again"], done


def test_command_that_finishes_after_a_swallowed_interrupt_exits_130() -> None:
    done = _python(
        _SWALLOW
        + """
from rasterserver.cli import main
raise SystemExit(main(["--help"]))
"""
    )
    assert done.returncode == 130, done
    assert done.stderr.rstrip().endswith("interrupted"), done


def test_no_interrupt_no_change() -> None:
    done = _python("""
from rasterserver.interrupts import install, interrupted, raise_if_interrupted
from rasterserver.cli import main
install()
raise_if_interrupted()
raise SystemExit(main(["--help"]) + 10 * interrupted())
""")
    assert done.returncode == 0, done


@pytest.mark.parametrize("inherited", [signal.SIG_IGN, signal.SIG_DFL])
def test_a_handler_other_than_pythons_is_kept(inherited: signal.Handlers) -> None:
    # nohup starts a command with SIGINT ignored; it must stay ignored
    done = _python(f"""
import signal
signal.signal(signal.SIGINT, signal.{inherited.name})
from rasterserver.interrupts import install
install()
print(signal.getsignal(signal.SIGINT) is signal.{inherited.name})
""")
    assert done.stdout.strip() == "True", done
