"""The ablation of the numbering's safeguards: run as users run it (a fresh process), and
its totals on hand-made rows."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from bench_scripts import load_script, run_script


def _run(*args: str) -> Any:
    return run_script("numbering_ablation", *args)


def _module() -> Any:
    return load_script("numbering_ablation")


def test_an_unknown_step_is_refused_with_the_steps_listed(tmp_path: Path) -> None:
    out = tmp_path / "a.json"
    done = _run("--only", "column-islands,nope", "--out", str(out))
    assert done.returncode == 2
    assert "unknown step(s) nope" in done.stderr
    assert "column-blocks" in done.stderr  # the steps are listed
    assert not out.exists()


def test_an_unknown_raster_and_an_empty_range_are_refused(tmp_path: Path) -> None:
    done = _run("--raster", "nope", "--out", str(tmp_path / "a.json"))
    assert done.returncode == 2
    assert "mseq8-35to65" in done.stderr
    done = _run("--scenes", "0", "--out", str(tmp_path / "a.json"))
    assert done.returncode == 2
    assert "--scenes must be at least 1" in done.stderr


def test_a_scene_is_numbered_with_each_step_off_and_its_frame_kept(tmp_path: Path) -> None:
    """Scene 2 through the default code: the installed numbering and two steps off; the
    rendered frame is kept in the cache and read again by the second run."""
    cache, out = tmp_path / "frames", tmp_path / "a.json"
    args = ("--first-seed", "2", "--scenes", "1", "--workers", "1", "--cache", str(cache),
            "--only", "column-islands,groups", "--out", str(out))  # fmt: skip
    done = _run(*args)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(out.read_text())
    assert summary["scenes"] == 1 and summary["error_seeds"] == []
    assert list(summary["steps"]) == ["column-islands", "groups"]
    base = summary["installed"]
    assert 90.0 < base["back_coverage"] <= 100.0
    for step in summary["steps"].values():
        assert step["catches"] == step["wrong_peaks"] - base["wrong_peaks"]
    # groups number more: switched off, they can only cost the back
    assert summary["steps"]["groups"]["costs_back_points"] <= 0.0
    assert "column-islands" in done.stdout  # the table
    assert [p.name for p in cache.iterdir()] == ["scene-2.npz"]
    again = _run(*args)
    assert again.returncode == 0, again.stderr[-2000:]
    assert json.loads(out.read_text()) == summary


def test_totals_count_scenes_with_errors_apart_and_survive_no_scene() -> None:
    ablation = _module()
    rows = [
        {"seed": 1, "back_crossings": 100, "installed": [0, 97], "line-ends": [3, 98]},
        {"seed": 2, "back_crossings": 300, "installed": [1, 291], "line-ends": [1, 295]},
        {"seed": 3, "error": "ValueError: boom"},
    ]
    summary = ablation.summarise(rows, ["line-ends"])
    assert summary["scenes"] == 2 and summary["error_seeds"] == [3]
    assert summary["installed"] == {
        "wrong_peaks": 1,
        "scenes_with_wrong": 1,
        "back_coverage": 97.0,
    }
    step = summary["steps"]["line-ends"]
    assert (step["wrong_peaks"], step["scenes_with_wrong"], step["catches"]) == (4, 2, 3)
    assert step["back_coverage"] == 98.25 and step["costs_back_points"] == 1.25
    empty = ablation.summarise([{"seed": 4, "error": "x"}], ["line-ends"])
    assert empty["scenes"] == 0 and empty["installed"]["back_coverage"] == 0.0
