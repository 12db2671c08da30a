"""The real-body benchmark's choice of scenes: one code's scenes, or every scene through a
held-out raster (run as users run it, in a fresh process)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from rasterserver_plugins.peak_detection import VERSION_5

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "real_bodies.py"


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300
    )


def test_raster_and_code_exclude_each_other(tmp_path: Path) -> None:
    out = tmp_path / "run.jsonl"
    done = _run("--raster", "mseq8-35to65", "--code", "mseq7", "--out", str(out))
    assert done.returncode == 2
    assert "--raster and --code exclude each other" in done.stderr
    assert not out.exists()


def test_an_unknown_raster_is_refused_by_name(tmp_path: Path) -> None:
    done = _run("--raster", "nope", "--out", str(tmp_path / "run.jsonl"))
    assert done.returncode == 2
    assert "mseq8-35to65" in done.stderr  # the choices are listed


def test_a_code_keeps_only_its_scenes_and_a_raster_replaces_the_code(tmp_path: Path) -> None:
    """Seeds 0-3 cover the four codes (``seed % 4``): ``--code mseq7`` scores seed 1 only;
    ``--raster`` scores both seeds of its range through the held-out raster."""
    out = tmp_path / "code.jsonl"
    done = _run("--first-seed", "0", "--scenes", "4", "--code", "mseq7", "--workers", "1",
                "--out", str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    rows = [json.loads(x) for x in out.read_text().splitlines() if x.strip()]
    assert [(r["seed"], r["code"]) for r in rows] == [(1, "mseq7")]
    # the same file, resumed through another raster: refused, not mixed
    done = _run("--first-seed", "0", "--scenes", "4", "--raster", "mseq8-35to65", "--out", str(out))
    assert done.returncode != 0
    assert "other stages" in done.stderr
    assert len(out.read_text().splitlines()) == 1
    out = tmp_path / "raster.jsonl"
    done = _run("--first-seed", "2", "--scenes", "2", "--raster", "mseq8-35to65",
                "--workers", "1", "--out", str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    rows = [json.loads(x) for x in out.read_text().splitlines() if x.strip()]
    assert sorted((r["seed"], r["code"]) for r in rows) == [
        (2, "mseq8-35to65"),
        (3, "mseq8-35to65"),
    ]
    assert "error" not in rows[0] and rows[0]["peaks"] > 0
    summary = json.loads(done.stdout[done.stdout.index("{") :])
    assert list(summary["per_code"]) == ["mseq8-35to65"]


def test_a_posture_keeps_only_its_scenes_and_an_empty_choice_is_refused(tmp_path: Path) -> None:
    """Seed 0's body has its hands on the hips and seed 1's arms are away (``random_body``'s
    draw): ``--posture hips`` over seeds 0-1 scores seed 0 only, with the posture in the
    summary; no scene of seeds 0-3 is seen through ``mseq7`` with hands on the hips, which
    is refused by name before anything is written."""
    out = tmp_path / "hips.jsonl"
    done = _run("--first-seed", "0", "--scenes", "4", "--code", "mseq7", "--posture", "hips",
                "--out", str(out))  # fmt: skip
    assert done.returncode == 2
    assert "no scene of seeds 0-3 is seen through mseq7 with arms hips" in done.stderr
    assert not out.exists()
    done = _run("--first-seed", "0", "--scenes", "2", "--posture", "hips", "--workers", "1",
                "--out", str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    rows = [json.loads(x) for x in out.read_text().splitlines() if x.strip()]
    assert [(r["seed"], r["posture"]) for r in rows] == [(0, "hips")]
    summary = json.loads(done.stdout[done.stdout.index("{") :])
    assert list(summary["per_posture"]) == ["hips"]
    assert summary["per_posture"]["hips"]["scenes"] == 1


def _bench():  # type: ignore[no-untyped-def]
    sys.path.insert(0, str(SCRIPT.parent))
    import real_bodies

    return real_bodies


def test_wrong_peaks_on_the_back_are_those_matched_to_the_backs_crossings() -> None:
    import numpy as np

    bench = _bench()
    on_back = np.array([True, False, True])
    wrong = np.array([True, True, True, False])
    crossing = np.array([0, 1, -1, 2])  # the third wrong peak matches no crossing
    assert bench.on_the_back(wrong, crossing, on_back).tolist() == [True, False, False, False]
    none = np.zeros(0, dtype=bool)
    assert bench.on_the_back(none, np.zeros(0, dtype=np.int64), on_back).size == 0
    assert bench.on_the_back(wrong, crossing, none).tolist() == [False] * 4


def test_a_cloths_wrong_peaks_are_not_on_the_back() -> None:
    """Kept scene 7770 (tests/data/scenes) with numbering version 20, peaks version 4 and
    line order version 1: four peaks of a cloth below the waistband numbered wrongly, none
    of them on the back; the summary counts them apart."""
    bench = _bench()
    frame = bench.Frame.load(SCRIPT.parents[1] / "tests" / "data" / "scenes" / "scene-7770.npz")
    v20 = {"one_sided_peaks": 0, "pair_shift": False, "shift_block": 0,
           "linked_one_sided": 0, "final_order": False, "meet_tolerance": 0.0,
           "outer_gap": 0.0}  # fmt: skip
    order_1 = {"gap_ratio": 1.6}
    peaks_4 = {"flank_tolerance": 0.0, **VERSION_5}  # in version 6
    bench._init(None, {"numbers": v20, "peaks": peaks_4, "order": order_1})
    row = bench.score_frame(frame)
    bench._init(None, None)
    assert row["wrong_peaks"] == 4 and row["wrong_objects"] == ["clothing"]
    assert row["wrong_on_back"] == 0


def test_a_frame_is_kept_through_a_file_of_the_writing_process(tmp_path: Path) -> None:
    """Two runs sharing a frame folder may render one scene at once: each writes its own
    temporary file and replaces the frame whole (a shared temporary file corrupted one)."""
    import os

    import numpy as np

    bench = _bench()
    frame = bench.Frame.load(SCRIPT.parents[1] / "tests" / "data" / "scenes" / "scene-7770.npz")
    path = tmp_path / "scene-7770.npz"
    other = tmp_path / "scene-7770.tmp.npz"  # what a run of the old code was writing
    other.write_bytes(b"half-written")
    frame.save(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([other.name, path.name])
    assert not (tmp_path / f"scene-7770.{os.getpid()}.tmp.npz").exists()
    again = bench.Frame.load(path)
    assert again.seed == frame.seed and np.array_equal(again.image, frame.image)
