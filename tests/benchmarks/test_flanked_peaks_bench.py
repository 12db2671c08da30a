"""The flanked-peaks benchmark run as users run it (a fresh process); the rule itself is
tested in ``tests/plugins/test_flanked_peaks.py``."""

from __future__ import annotations

import json
from pathlib import Path

from bench_scripts import run_script


def test_bad_arguments_are_refused(tmp_path: Path) -> None:
    out = tmp_path / "f.json"
    done = run_script("flanked_peaks", "--raster", "nope", "--out", str(out))
    assert done.returncode == 2 and "mseq8-35to65" in done.stderr
    done = run_script("flanked_peaks", "--area-ratio", "0.5", "--out", str(out))
    assert done.returncode == 2 and "--area-ratio >= 1" in done.stderr
    assert not out.exists()


def test_a_scene_is_scored_both_ways(tmp_path: Path) -> None:
    cache, out = tmp_path / "frames", tmp_path / "f.json"
    done = run_script(
        "flanked_peaks", "--first-seed", "2", "--scenes", "1", "--workers", "1",
        "--cache", str(cache), "--out", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(out.read_text())
    assert summary["scenes"] == 1 and summary["error_seeds"] == []
    without, kept = summary["unflanked"], summary["flanked"]
    assert 90.0 < without["back_coverage"] <= kept["back_coverage"] <= 100.0
    assert kept["dropped"] <= without["dropped"]
    assert 0.0 < kept["rec_rms"] < 0.1
    assert summary["rule"] == {"tolerance": 0.4, "span": 1.5, "area_ratio": 1.5, "run_on": 1.0}
