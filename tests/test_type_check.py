"""Issue 17: the package and the built-in plugins type-check clean under mypy.

The configuration is ``[tool.mypy]`` in pyproject.toml (the files, the checks, the few libraries
without types); this runs the same command a developer runs, ``mypy`` from the repository root.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_mypy_is_clean_on_the_package_and_plugins() -> None:
    # A real subprocess: mypy reads [tool.mypy] from the working directory's pyproject.toml.
    done = subprocess.run(
        [sys.executable, "-m", "mypy"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=540,
        check=False,
    )
    report = (done.stdout + done.stderr).strip()
    assert done.returncode == 0, f"mypy found type errors:\n{report}"
    assert "no issues found" in report, report
