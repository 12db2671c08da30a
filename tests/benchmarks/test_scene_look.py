"""One scene looked at closely (``benchmarks/scene_look.py``), run as users run it: a fresh
process, on a frame kept in ``tests/data/scenes``."""

from __future__ import annotations

import json
from pathlib import Path

from bench_scripts import run_script
from rasterserver_plugins.peak_detection import VERSION_5

SCENES = Path(__file__).resolve().parents[1] / "data" / "scenes"
#: peaks version 5 in version 6, on which the scene's case was found
PEAKS_5 = VERSION_5
#: numbering version 21 (``docs/numbering-versions.md``) on line order version 1
V21 = json.dumps(
    {
        "numbers": {"pair_shift": False, "shift_block": 0},
        "order": {"gap_ratio": 1.6},
        "peaks": PEAKS_5,
    }
)


def test_a_cloth_block_is_listed_and_drawn_against_the_version_that_refuses_it(
    tmp_path: Path,
) -> None:
    """Scene 7728 through the twin raster: version 21 numbers a cloth block a line low
    (tests/plugins/test_line_numbering.py), on line order version 1 and peaks version 5;
    the installed numbering on those refuses it."""
    png = tmp_path / "look.png"
    args = ("--seed", "7728", "--raster", "mseq8b-35to65", "--cache", str(SCENES))
    against = json.dumps({"order": {"gap_ratio": 1.6}, "peaks": PEAKS_5})
    done = run_script("scene_look", *args, "--params", V21, "--against", against, "--png", str(png))
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert report["wrong_peaks"] >= 30 and report["wrong_peaks_against"] == 0
    assert sum(line["wrong_peaks"] for line in report["wrong_lines"]) == report["wrong_peaks"]
    assert all(line["objects"] == ["clothing"] for line in report["wrong_lines"])
    for line in report["wrong_lines"]:  # numbered a line low
        assert all(t > line["number"] for t in line["true_numbers"])
    # what the installed version refuses with the block is a sliver of the back
    assert report["back_only_params"] <= 0.001 * report["back_crossings"]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_parameters_that_are_not_stage_maps_are_refused(tmp_path: Path) -> None:
    for bad, why in (("{", "--params is not JSON"), ('{"peaks": 3}', "must map stages")):
        done = run_script("scene_look", "--seed", "7728", "--params", bad)
        assert done.returncode == 2 and why in done.stderr, done.stderr
    done = run_script("scene_look", "--seed", "7728", "--box", "1,2,3")
    assert done.returncode == 2 and "four integers" in done.stderr


def test_a_scene_rendered_once_is_kept_in_a_new_frame_folder(tmp_path: Path) -> None:
    folder = tmp_path / "frames" / "new"
    first = run_script("scene_look", "--seed", "7044", "--cache", str(folder))
    assert first.returncode == 0, first.stderr[-2000:]
    kept = folder / "scene-7044.npz"
    assert kept.is_file()
    stamp = kept.stat().st_mtime_ns
    again = run_script("scene_look", "--seed", "7044", "--cache", str(folder))
    assert again.returncode == 0 and again.stdout == first.stdout  # read, not rendered anew
    assert kept.stat().st_mtime_ns == stamp
