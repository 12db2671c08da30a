"""``rasterserver analyse`` (frames, no archive) and ``rasterserver show`` (an archived
acquisition): the installed command in fresh processes on simulated frames."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from rasterserver.archive import Archive
from rasterserver.config import Settings, sqlite_url
from rasterserver.records_analysis import LANDMARKS

EXE = Path(sys.executable).with_name("rasterserver")


def run(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """The installed command in a fresh process."""
    return subprocess.run(
        [str(EXE), *args], capture_output=True, text=True, timeout=600, check=False, env=env
    )


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two simulated visits' frames (a progressing scoliosis), the station's calibration
    and raster as `rasterserver simulate` writes them, and broken inputs."""
    folder = tmp_path_factory.mktemp("analyse")
    made = run(
        "simulate",
        "back",
        "--preset",
        "moderate",
        "--visits",
        "2",
        "--supersample",
        "2",
        "--out",
        str(folder),
    )
    assert made.returncode == 0, made.stderr
    visit = folder / "visit-01"
    calibration = json.loads((visit / "calibration.json").read_text())
    assert calibration["gravity"] == [0.0, 1.0, 0.0]
    del calibration["gravity"]
    no_gravity = folder / "no-gravity.json"
    no_gravity.write_text(json.dumps(calibration))
    frame = cv2.imread(str(visit / "frame.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(folder / "black.png"), np.zeros_like(frame))
    cv2.imwrite(str(folder / "small.png"), frame[::2, ::2])
    return {
        "frame": visit / "frame.png",
        "second": folder / "visit-02" / "frame.png",
        "calibration": visit / "calibration.json",
        "raster": visit / "raster.json",
        "no-gravity": no_gravity,
        "black": folder / "black.png",
        "small": folder / "small.png",
    }


def _check_document(document: dict, frames: int) -> None:
    assert document["format"] == "rasterserver.back-shape/1"
    assert document["frame"]["unit"] == "mm" and document["frame"]["gravity"] == [0, 1, 0]
    assert list(document["landmarks"]) == list(LANDMARKS)
    for name, point in document["landmarks"].items():
        assert point is None or (len(point) == 3 and all(isinstance(v, float) for v in point)), name
    assert list(document["sagittal_points"]) == ["ICT", "KA", "ITL", "LA", "ILS"]
    found = {r["what"] for r in document["reasons"]}
    for name in LANDMARKS:  # found, or said why not
        assert document["landmarks"][name] is not None or name in found, name
    assert document["parameters"], "the analysis gives parameters"
    for entry in document["parameters"].values():
        assert set(entry) == {"value", "unit", "spread"} and entry["unit"] in ("mm", "deg", "1")
    assert len(document["frames"]) == frames


def test_analyse_prints_landmarks_and_parameters(files, tmp_path: Path) -> None:
    done = run("analyse", str(files["frame"]), "--calibration", str(files["calibration"]))
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert out.startswith("back-shape analysis of frame.png")
    assert "calibration world frame" in out
    for name in LANDMARKS:
        assert f"\n  {name} " in out
    assert "Trunk length VP-DM" in out


def test_analyse_json_and_report(files, tmp_path: Path) -> None:
    report = tmp_path / "report.png"
    done = run(
        "analyse",
        str(files["frame"]),
        "--calibration",
        str(files["calibration"]),
        "--raster",
        str(files["raster"]),
        "--json",
        "--report",
        str(report),
    )
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)  # one object, nothing else on stdout
    _check_document(document, frames=1)
    assert document["landmarks"]["VP"] is not None and document["landmarks"]["DM"] is not None
    assert all(e["spread"] is None for e in document["parameters"].values())
    page = cv2.imread(str(report))
    assert page is not None and page.shape[1] > page.shape[0] > 800
    assert f"report written to {report}" in done.stderr


def test_analyse_several_frames_gives_mean_and_spread(files) -> None:
    done = run(
        "analyse",
        str(files["frame"]),
        str(files["second"]),
        "--calibration",
        str(files["calibration"]),
        "--json",
    )
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)
    _check_document(document, frames=2)
    # two visits of a progressing curve: the frames differ, so the spread is measured
    spreads = [e["spread"] for e in document["parameters"].values()]
    assert all(s is None or s >= 0 for s in spreads) and any(s for s in spreads)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["{black}", "--calibration", "{calibration}"], "no back-shape analysis of black.png"),
        (["{frame}", "--calibration", "{no-gravity}"], "gravity"),
        (["{small}", "--calibration", "{calibration}"], "small.png: the frame is 302x288"),
        (["{frame}", "--calibration", "{frame}"], "frame.png: not a JSON calibration"),
        (["{frame}", "--calibration", "missing.json"], "missing.json: no such calibration file"),
        (["missing.png", "--calibration", "{calibration}"], "missing.png: no such file"),
        (["{frame}", "--calibration", "{calibration}", "--report", "out.txt"], ".png or .pdf"),
        (
            ["{frame}", "--calibration", "{calibration}", "--report", "no/such/dir/r.png"],
            "no/such/dir",
        ),
        (["{frame}", "--calibration", "{calibration}", "--stage", "analysis"], "KIND=PLUGIN"),
    ],
)
def test_analyse_refuses_bad_input_with_a_sentence(files, tmp_path: Path, args, message) -> None:
    argv = [a.format(**{k: str(v) for k, v in files.items()}) for a in args]
    done = subprocess.run(
        [str(EXE), "analyse", *argv],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
        cwd=tmp_path,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.startswith("error: ") and message in done.stderr
    assert "Traceback" not in done.stderr and done.stdout == ""
    assert list(tmp_path.iterdir()) == []  # no report, no partial file


@pytest.fixture(scope="module")
def archived(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, str], str]:
    """An archive (SQLite) with one simulated visit ingested and not processed yet."""
    root = tmp_path_factory.mktemp("show") / "archive"
    env = {**os.environ, "RASTERSERVER_ARCHIVE": str(root)}
    env.pop("RASTERSERVER_DATABASE_URL", None)
    made = run(
        "simulate",
        "back",
        "--supersample",
        "2",
        "--out",
        str(root.parent / "sim"),
        "--ingest",
        "--patient",
        "P-SHOW",
        env=env,
    )
    assert made.returncode == 0, made.stderr
    with Archive(Settings(archive=root, database_url=sqlite_url(root))) as archive:
        (acq,) = archive.acquisitions(patient="P-SHOW")
    return env, acq.uid


def test_show_an_archived_acquisition(archived, tmp_path: Path) -> None:
    env, uid = archived
    missing = run("show", uid, env=env)
    assert missing.returncode == 3
    assert (
        f"has no stored analysis yet: process it first (`rasterserver process {uid}`"
        in missing.stderr
    )
    assert run("show", "f" * 32, env=env).returncode == 3
    report = tmp_path / "report.pdf"
    shown = run("show", uid, "--process", "--report", str(report), env=env)
    assert shown.returncode == 0, shown.stderr
    assert shown.stdout.startswith(f"acquisition {uid} (patient P-SHOW, acquired ")
    assert "calibration simulator:1" in shown.stdout and "Trunk length VP-DM" in shown.stdout
    assert report.read_bytes().startswith(b"%PDF")
    # stored now: read back without processing, with each frame's provenance
    again = run("show", uid, "--json", env=env)
    assert again.returncode == 0, again.stderr
    document = json.loads(again.stdout)
    _check_document(document, frames=1)
    assert document["uid"] == uid
    provenance = document["frames"][0]["provenance"]
    assert provenance["stage"] == "analysis" and provenance["plugin"] == "analysis.back-shape"
    # show stored it like process does: process reuses it and computes only the mesh
    processed = json.loads(run("process", uid, "--json", env=env).stdout)
    assert (processed["computed"], processed["reused"]) == (1, 7)
