"""The coordinator cost benchmark's command line, run as users run it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "coordinator_cost.py"


def test_help_explains_the_argument_instead_of_reading_it_as_a_count() -> None:
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--help"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "count" in done.stdout and "reprocess.py" in done.stdout
