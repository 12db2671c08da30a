"""The one-page back-shape report: PNG and PDF, degenerate analyses, files, lazy import."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from backshape_truth import simulated, truth_backshape

from rasterserver.analysis import Analysis, AnalysisRefusedError, FrameAnalysis
from rasterserver.analysis_report import render_report, write_report
from rasterserver.errors import InputError
from rasterserver.records_analysis import LANDMARKS, BackShape, combine


@pytest.fixture(scope="module")
def back() -> tuple[np.ndarray, object, dict]:
    return simulated("moderate")


def _analysis(*frames: FrameAnalysis) -> Analysis:
    return Analysis(
        frames=frames,
        combined=combine([f.shape for f in frames]),
        calibration="clinic-1:3",
        gravity=[0.0, 1.0, 0.0],
        plugin={"plugin": "analysis.back-shape", "version": "1"},
    )


def _decoded(data: bytes) -> np.ndarray:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image


def test_png_page_with_maps_profiles_and_table(back) -> None:
    _image, surface, truth = back
    shape = truth_backshape(truth, surface, drop=("SP",))
    page = _decoded(
        render_report(
            _analysis(FrameAnalysis("frame.png", shape, surface)),
            header=["acquisition 0123", "patient P-1"],
        )
    )
    assert page.shape == (990, 1815, 3)  # 16.5 x 9 in at 110 dpi: landscape
    # drawn, not blank: the maps' colours and the midline's red are on the page
    assert page.std() > 40
    red = (page[..., 2] > 150) & (page[..., 1] < 60) & (page[..., 0] < 60)
    assert red.sum() > 200


def test_a_midline_with_refused_levels_draws_with_gaps(back) -> None:
    # analysis version 10 refuses the midline (NaN rows) where the rotation's window lacks
    # surface: the page draws the measured pieces
    import dataclasses

    _image, surface, truth = back
    shape = truth_backshape(truth, surface)
    m = len(shape.midline)
    assert m > 10
    gap = slice(m // 3, m // 3 + max(m // 10, 2))
    midline, rotation = shape.midline.copy(), shape.surface_rotation.copy()
    midline[gap], rotation[gap] = np.nan, np.nan
    holed = dataclasses.replace(shape, midline=midline, surface_rotation=rotation)
    page = _decoded(render_report(_analysis(FrameAnalysis("frame.png", holed, surface))))
    assert page.std() > 40


def test_pdf_is_one_page(back) -> None:
    _image, surface, truth = back
    data = render_report(
        _analysis(FrameAnalysis("frame.png", truth_backshape(truth, surface), surface)),
        fmt="pdf",
    )
    assert data.startswith(b"%PDF")
    assert len(re.findall(rb"/Type\s*/Page(?!s)", data)) == 1


def test_degenerate_analyses_still_draw(back) -> None:
    _image, surface, truth = back
    # no landmark at all, several frames, one refused, no surface loaded
    lost = truth_backshape(truth, surface, drop=LANDMARKS)
    analysis = _analysis(
        FrameAnalysis("a.png", BackShape.empty("no back in view")),
        FrameAnalysis("b.png", lost),
        FrameAnalysis("c.png", truth_backshape(truth, surface, drop=LANDMARKS, scale=1.1)),
    )
    assert _decoded(render_report(analysis)).std() > 10


def test_refusals(back, tmp_path: Path) -> None:
    _image, surface, truth = back
    empty = _analysis(FrameAnalysis("frame.png", BackShape.empty("no back in view")))
    with pytest.raises(AnalysisRefusedError, match="no back in view"):
        render_report(empty)
    good = _analysis(FrameAnalysis("frame.png", truth_backshape(truth, surface), surface))
    with pytest.raises(InputError, match="report format 'svg'"):
        render_report(good, fmt="svg")
    with pytest.raises(InputError, match=r"\.png or \.pdf"):
        write_report(good, tmp_path / "report.txt")
    with pytest.raises(InputError, match="no-such-folder"):
        write_report(good, tmp_path / "no-such-folder" / "report.png")
    written = write_report(good, tmp_path / "report.pdf")
    assert written.read_bytes().startswith(b"%PDF")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.pdf"]  # no temporary left


def test_matplotlib_is_imported_only_for_a_report() -> None:
    code = (
        "import sys, rasterserver.cli, rasterserver.analysis, rasterserver.api.app; "
        "print('matplotlib' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "False"
