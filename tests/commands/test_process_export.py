"""``rasterserver process`` and ``export`` end to end, on SQLite and PostgreSQL."""

from __future__ import annotations

import json
from pathlib import Path

import geometry_truth as gt
import numpy as np
import open3d as o3d
import pytest

from rasterserver.cli import main
from rasterserver.config import Settings


@pytest.fixture
def setup(settings: Settings):
    frames = {"back": gt.rendering("back").image, "black": np.zeros((604, 576), np.uint8)}
    archive, uids = gt.archive_with_frames(settings, frames)
    archive.close()
    base = ["--archive", str(settings.archive), "--database-url", settings.database_url]

    def run(*args: str) -> int:
        return main([*base, *args])

    return run, uids


def test_process_then_reuse_then_export(setup, tmp_path: Path, capsys) -> None:
    cli, uids = setup
    back = uids["back"]
    assert cli("process", back) == 0
    out = capsys.readouterr().out
    # the default targets: the mesh and the back-shape analysis, sharing the surface
    assert f"{back}\tdone\t8 computed, 0 reused" in out
    assert cli("process", back, "--json") == 0
    (line,) = capsys.readouterr().out.splitlines()
    assert json.loads(line) | {"uid": back} == {
        "uid": back,
        "status": "done",
        "computed": 0,
        "reused": 8,
        "reason": json.loads(line)["reason"],
        "error": "",
    }
    for fmt in ("ply", "obj", "stl"):
        path = tmp_path / f"back.{fmt}"
        assert cli("export", back, "--format", fmt, "-o", str(path)) == 0
        mesh = o3d.io.read_triangle_mesh(str(path))
        assert len(mesh.triangles) > 30_000
    vertices = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "back.ply")).vertices)
    assert gt.rms(gt.distance_to_scene(gt.scene("back"), vertices)) <= 0.2
    csv = tmp_path / "points.csv"
    assert cli("export", back, "--format", "csv", "-o", str(csv)) == 0
    header, *rows = csv.read_text().splitlines()
    assert header == "x_mm,y_mm,z_mm,line_number,column,row,peak_area"
    assert 15_000 < len(rows) < 30_000
    smoothed = tmp_path / "smoothed.ply"
    assert cli("export", back, "-f", "ply", "--what", "smoothed", "-o", str(smoothed)) == 0
    cloud = o3d.t.io.read_point_cloud(str(smoothed))
    assert len(rows) / 3 == pytest.approx(cloud.point.positions.shape[0], rel=0.05)
    assert "number" in cloud.point


def test_selection_by_patient_and_unprocessed(setup, capsys) -> None:
    cli, uids = setup
    assert cli("process", "--all-unprocessed", "--until", "peaks") == 0
    out = capsys.readouterr().out
    assert all(uid in out for uid in uids.values())
    assert cli("process", "--all-unprocessed") == 0
    assert "nothing to process" in capsys.readouterr().err
    assert cli("process", "--patient", "P1", "--until", "lines") == 0
    assert capsys.readouterr().out.count("\tdone\t") == 2
    assert cli("process") == 2
    assert "--all-unprocessed" in capsys.readouterr().err


def test_empty_results_and_failures_are_reported(setup, tmp_path: Path, capsys) -> None:
    cli, uids = setup
    assert cli("process", uids["black"]) == 0
    out = capsys.readouterr().out
    assert "done" in out and "no peaks" in out  # an empty result, with its reason
    assert cli("export", uids["black"], "-f", "ply", "-o", str(tmp_path / "m.ply")) == 2
    assert "no mesh to write" in capsys.readouterr().err
    assert cli("station", "add", "clinic-2") == 0
    cal = gt.station().save(tmp_path / "cal.json")
    assert cli("station", "add-calibration", "clinic-2", str(cal)) == 0
    capsys.readouterr()
    # a calibration of another station: bad input for this acquisition (exit 2)
    assert cli("process", uids["back"], "--calibration", "clinic-2:1") == 2
    captured = capsys.readouterr()
    assert "failed" in captured.out and "station 'clinic-1'" in captured.out
    assert "1 of 1 acquisition(s) failed" in captured.err
    assert cli("process", uids["back"], "--calibration", "clinic-1:x") == 2
    # issue 11, defect 6: not found is 3 (the README's table), not 1
    assert cli("process", uids["back"], "--calibration", "clinic-1:9") == 3
    assert "no calibration version 9" in capsys.readouterr().err  # refused before any work
    assert cli("process", "f" * 32) == 3
    assert "unknown acquisition" in capsys.readouterr().out
    assert cli("process", uids["back"], "--stage", "peaks=no-such-plugin") == 3
    assert "no stage plugin named 'no-such-plugin'" in capsys.readouterr().err
    # failures of different kinds: 1, each listed
    assert cli("process", "f" * 32, uids["back"], "--calibration", "clinic-2:1") == 1
    assert capsys.readouterr().out.count("\tfailed\t") == 2


def test_export_needs_a_processed_acquisition(setup, tmp_path: Path, capsys) -> None:
    cli, uids = setup
    out = tmp_path / "m.ply"
    assert cli("export", uids["back"], "-f", "ply", "-o", str(out)) == 3
    assert "rasterserver process" in capsys.readouterr().err
    assert cli("export", uids["back"], "-f", "obj", "--what", "points", "-o", str(out)) == 2
    assert cli("export", uids["back"], "-f", "csv", "--what", "mesh", "-o", str(out)) == 2
    assert not out.exists()


@pytest.mark.slow
def test_process_on_a_local_dask_cluster(tmp_path: Path, capsys, monkeypatch) -> None:
    pytest.importorskip("distributed")
    from rasterserver.config import sqlite_url

    settings = Settings(archive=tmp_path / "archive", database_url=sqlite_url(tmp_path / "a"))
    archive, uids = gt.archive_with_frames(settings, {"back": gt.rendering("back").image})
    archive.close()
    monkeypatch.delenv("RASTERSERVER_DASK_SCHEDULER", raising=False)
    base = ["--archive", str(settings.archive), "--database-url", settings.database_url]
    assert main([*base, "process", uids["back"], "--dask", "--until", "surface"]) == 0
    assert "6 computed, 0 reused" in capsys.readouterr().out


def test_patient_frame_export_is_refused_without_a_body_frame(
    settings: Settings, tmp_path: Path, capsys
) -> None:
    # a sphere has a mesh but no back: the analysis finds no VP, DL, DR, so no patient frame
    archive, uids = gt.archive_with_frames(settings, {"sphere": gt.rendering("sphere").image})
    archive.close()
    base = ["--archive", str(settings.archive), "--database-url", settings.database_url]
    assert main([*base, "process", uids["sphere"]]) == 0
    capsys.readouterr()
    out = tmp_path / "sphere.ply"
    assert main([*base, "export", uids["sphere"], "-f", "ply", "-o", str(out),
                 "--frame", "patient"]) == 2  # fmt: skip
    assert "no body-fixed frame" in capsys.readouterr().err
    assert not out.exists() and not out.with_name("sphere.ply.json").exists()
    assert main([*base, "export", uids["sphere"], "-f", "ply", "-o", str(out)]) == 0
    assert json.loads(out.with_name("sphere.ply.json").read_text())["frame"]["name"] == "station"
