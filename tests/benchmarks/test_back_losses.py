"""Where the back's crossings are lost: run as users run it (a fresh process), and its
pieces on hand-made arrays."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from bench_scripts import load_script, run_script


def _module() -> Any:
    return load_script("back_losses")


def test_an_unknown_raster_and_an_empty_range_are_refused(tmp_path: Path) -> None:
    out = tmp_path / "l.json"
    done = run_script("back_losses", "--raster", "nope", "--out", str(out))
    assert done.returncode == 2
    assert "mseq8-35to65" in done.stderr  # the rasters are listed
    done = run_script("back_losses", "--scenes", "0", "--out", str(out))
    assert done.returncode == 2
    assert "--scenes must be at least 1" in done.stderr
    assert not out.exists()


def test_a_scene_s_back_is_accounted_for_whole(tmp_path: Path) -> None:
    """Scene 2 through the default code: the categories and the coverage add up to the
    whole back, and the coverage is the one ``real_bodies.py`` scores."""
    cache, out = tmp_path / "frames", tmp_path / "l.json"
    args = ("--first-seed", "2", "--scenes", "1", "--workers", "1", "--cache", str(cache),
            "--out", str(out))  # fmt: skip
    done = run_script("back_losses", *args)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(out.read_text())
    assert summary["scenes"] == 1 and summary["error_seeds"] == []
    shares = summary["shares"]
    assert list(shares) == list(_module().CATEGORIES)
    assert abs(sum(s["all"] for s in shares.values()) - 100.0) < 0.01
    for s in shares.values():
        assert abs(s["top"] + s["below"] - s["all"]) < 0.0002
    scores = tmp_path / "bodies.jsonl"
    bodies = run_script("real_bodies", *args[:-2], "--out", str(scores))
    assert bodies.returncode == 0, bodies.stderr[-2000:]
    scored = json.loads(scores.read_text().splitlines()[0])
    assert shares["covered"]["all"] == round(
        100.0 * scored["back_covered"] / scored["back_crossings"], 4
    )
    # every crossing lost has its stage; some lie at the silhouette without a peak
    assert shares["covered"]["all"] > 90.0
    assert shares["no peak at an edge"]["all"] > 0.0
    assert "covered" in done.stdout  # the table


def test_the_top_of_the_back_is_the_first_crossings_of_each_column() -> None:
    mod = _module()
    column = np.array([5, 5, 5, 5, 5, 5, 5, 5, 5, 5, 7, 7])
    row = np.array([90.0, 10, 20, 30, 40, 50, 60, 70, 80, 5, 3, 1])
    on_back = np.array([True] * 9 + [False, True, True])
    top = mod.top_of_back(column, row, on_back)
    # column 5: row 5 is off the back; rows 10-80 are its first eight, row 90 the ninth
    assert top.tolist() == [False] + [True] * 8 + [False, True, True]
    assert not mod.top_of_back(column, row, np.zeros(12, dtype=bool)).any()


def test_a_crossing_beside_another_object_is_at_an_edge() -> None:
    mod = _module()
    obj = np.full((4, 10), 1)
    obj[:, 7:] = -1  # the background from column 7
    column, row = np.array([2, 5, 6, 7]), np.array([1.2, 1.0, 2.4, 3.0])
    assert mod.at_an_edge(obj, column, row).tolist() == [False, True, True, True]
    # the frame's own border is no edge
    assert not mod.at_an_edge(np.ones((3, 3), dtype=int), np.array([0]), np.array([0.0]))[0]
