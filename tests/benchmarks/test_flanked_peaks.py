"""The flanked-peaks screening: the rule on hand-made frames, and the script run as users run
it (a fresh process)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from bench_scripts import load_script, run_script


def _module() -> Any:
    return load_script("flanked_peaks")


def _frame(bump_row: float = 34.5, dim_right: bool = False, gaps: bool = False) -> np.ndarray:
    """A line at row 30.3 over 12 columns; in column 5 alone a second line at ``bump_row``
    makes the first one's bounding minima unequal (the detector drops it there)."""
    y = np.arange(64, dtype=float)[:, None]
    img = np.tile(20 + 150 * np.exp(-0.5 * ((y - 30.3) / 1.2) ** 2), (1, 12))
    img[:, 5] += 90 * np.exp(-0.5 * ((y[:, 0] - bump_row) / 1.2) ** 2)
    if dim_right:  # another surface from column 6 on: half the light
        img[:, 6:] = 20 + (img[:, 6:] - 20) * 0.5
    if gaps:  # the line does not run on two columns out
        img[:, [3, 7]] = 20
    return np.clip(img, 0, 255).astype(np.uint8)


def _at(peaks: Any, col: int) -> list[float]:
    return [round(float(r), 1) for c, r in zip(peaks.col, peaks.row, strict=True) if c == col]


def test_a_dropped_peak_flanked_by_its_line_is_kept() -> None:
    mod = _module()
    from rasterserver_plugins.peak_detection import detect_peaks

    img = _frame()
    installed = detect_peaks(img)
    assert _at(installed, 5) == [] and installed.dropped == 2
    kept = mod.flanked(img, mod.Rule())
    assert _at(kept, 5) == [30.3]  # the line's peak; the lone bump stays dropped
    assert kept.dropped == 1
    assert np.all(np.diff(kept.col) >= 0)  # still sorted by column
    # every installed peak is still there
    before = set(zip(installed.col.tolist(), installed.row.tolist(), strict=True))
    assert before <= set(zip(kept.col.tolist(), kept.row.tolist(), strict=True))
    # no tolerance: nothing kept
    none = mod.flanked(img, mod.Rule(tolerance=0.0))
    assert none.col.tolist() == installed.col.tolist() and none.dropped == 2


def test_flanks_of_unequal_area_or_a_line_that_does_not_run_on_keep_nothing() -> None:
    mod = _module()
    # an arm's edge: the flanks differ by twice in area
    assert _at(mod.flanked(_frame(dim_right=True), mod.Rule()), 5) == []
    assert _at(mod.flanked(_frame(dim_right=True), mod.Rule(area_ratio=2.5)), 5) == [30.3]
    # the line ends two columns out: kept only without the run-on test
    assert _at(mod.flanked(_frame(gaps=True), mod.Rule()), 5) == []
    assert _at(mod.flanked(_frame(gaps=True), mod.Rule(run_on=0.0)), 5) == [30.3]


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
    installed, kept = summary["installed"], summary["flanked"]
    assert 90.0 < installed["back_coverage"] <= 100.0
    assert kept["dropped"] <= installed["dropped"]
    assert 0.0 < kept["rec_rms"] < 0.1
    assert summary["rule"] == {"tolerance": 0.4, "span": 1.5, "area_ratio": 1.5, "run_on": 1.0}
