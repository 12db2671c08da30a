"""The numbering speed benchmark: variants on the same frames, run in a fresh process."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "numbering_speed.py"


def test_variants_are_timed_on_the_same_frames_and_full_passes_number_alike(
    tmp_path: Path,
) -> None:
    """One clinic frame through the held-out raster's twin: the installed numbering, version
    14's parameters and the full-passes variant are timed; the full passes give the same
    numbers; the frame is kept in the cache (a second run reads it)."""
    args = [sys.executable, str(SCRIPT), "--first-seed", "7099", "--frames", "1", "--repeat",
            "1", "--raster", "mseq8b-35to65", "--cache", str(tmp_path), "--variant",
            'v14={"detached_peaks": 0}', "--full-passes"]  # fmt: skip
    done = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert report["frames"] == 1 and report["full_passes_same_numbers"] is True
    assert set(report["ms_median"]) == {"installed", "v14", "installed, full passes"}
    assert all(ms > 0 for ms in report["ms_median"].values())
    assert (tmp_path / "scene-7099-mseq8b-35to65.npz").exists()


def test_help_explains_the_options() -> None:
    """``--help`` prints the options (a bare percent sign in a help text once broke it)."""
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--help"], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "--variant" in done.stdout and "seed % 4" in done.stdout
