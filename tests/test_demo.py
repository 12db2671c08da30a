"""The README's main job runs end to end on the embedded default and on PostgreSQL."""

from __future__ import annotations

from pathlib import Path

import open3d as o3d

from rasterserver.analysis import KEY_PARAMETERS
from rasterserver.archive import Archive
from rasterserver.config import Settings
from rasterserver.demo import DEMO_PATIENT, run_demo


def test_demo_simulates_ingests_processes_exports_and_verifies(
    settings: Settings, tmp_path: Path
) -> None:
    lines: list[str] = []
    result = run_demo(settings, visits=2, export_dir=tmp_path / "out", log=lines.append)
    assert result.problems == 0 and result.verified_frames == 2
    assert [o.status for o in result.outcomes] == ["done", "done"]
    assert len(result.meshes) == 2
    for path in result.meshes:
        mesh = o3d.io.read_triangle_mesh(str(path))
        assert len(mesh.triangles) > 1000
        # A back seen from the camera: a few hundred mm wide, in front of the origin plane.
        extent = mesh.get_axis_aligned_bounding_box().get_extent()
        assert 200 < extent[0] < 600 and 200 < extent[1] < 700
    # each visit's report beside its mesh, and the visits' parameters side by side at the end
    assert [p.name for p in result.reports] == [
        f"{DEMO_PATIENT}-visit-01-report.png",
        f"{DEMO_PATIENT}-visit-02-report.png",
    ]
    for path in result.reports:
        assert path.parent == result.meshes[0].parent
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert all(p and p["trunk_length"]["unit"] == "mm" for p in result.parameters)
    table = lines[lines.index("back-shape parameters (docs/analysis.md):") + 1 :]
    assert table[0].split() == ["parameter", "visit", "1", "visit", "2", "unit"]
    assert any(line.split()[:2] == ["Scoliosis", "angle"] for line in table)
    assert len(table) == 1 + len(KEY_PARAMETERS) and table == lines[-len(table) :]
    # the visits compared: registered, distance map and trends in one folder
    assert result.comparison is not None and result.comparison.parent == tmp_path / "out"
    assert {"report.html", "comparison.json", "trends.csv"} <= {
        p.name for p in result.comparison.iterdir()
    }
    assert any(line.startswith("comparison ") and "distance rms" in line for line in lines)
    with Archive(settings) as archive:
        assert len(archive.acquisitions(patient=DEMO_PATIENT)) == 2
    assert not any(DEMO_PATIENT in line for line in lines if "ingested" in line)
