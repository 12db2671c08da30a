"""The back-shape analysis service: frames in memory, archived acquisitions, the document.

BackShape records are built from the simulator's truth (:mod:`backshape_truth`), so what users
see is checked independently of how well the analysis plugin finds the landmarks.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from backshape_truth import simulated, truth_backshape

from rasterserver.analysis import (
    KEY_PARAMETERS,
    Analysis,
    AnalysisRefusedError,
    FrameAnalysis,
    acquisition_analysis,
    analyse_frames,
    ordered_parameters,
    parameter_columns,
    parameter_label,
)
from rasterserver.archive import Archive, FrameSource
from rasterserver.config import Settings
from rasterserver.errors import InputError, NotFoundError
from rasterserver.optics import default_station
from rasterserver.pipeline import Pipeline
from rasterserver.records_analysis import LANDMARKS, BackShape, combine
from rasterserver.simulated_visits import register_station


@pytest.fixture(scope="module")
def back() -> tuple[np.ndarray, object, dict]:
    """A rendered moderate scoliosis: image, reconstructed surface, truth (seconds: once)."""
    return simulated("moderate")


def _analysis(*frames: tuple[str, BackShape], surface=None) -> Analysis:
    parts = tuple(FrameAnalysis(name, shape, surface) for name, shape in frames)
    return Analysis(
        frames=parts,
        combined=combine([f.shape for f in parts]),
        calibration="default",
        gravity=[0.0, 1.0, 0.0],
        plugin={"plugin": "analysis.back-shape", "version": "1", "package": "rasterserver"},
    )


def test_several_frames_give_mean_and_spread(back) -> None:
    _image, surface, truth = back
    analysis = _analysis(
        ("a.png", truth_backshape(truth, surface)),
        ("b.png", truth_backshape(truth, surface, shift=(2.0, 0.0, 0.0), scale=1.1)),
    )
    document = analysis.check().document()
    length = truth["parameters"]["trunk_length"]["value"]
    assert document["parameters"]["trunk_length"] == {
        "value": pytest.approx(1.05 * length),
        "unit": "mm",
        "spread": pytest.approx(np.std([length, 1.1 * length], ddof=1)),
    }
    assert document["parameters"]["scoliosis_angle_deg"]["unit"] == "deg"
    vp = np.asarray(truth["landmarks"]["VP"]) + np.array([1.0, 0.0, 0.0])
    assert document["landmarks"]["VP"] == pytest.approx(list(vp))
    # the report draws the frame the maps and lines come from
    shown = analysis.shown_frame().shape
    assert shown.symmetry_line.tolist() == analysis.combined.symmetry_line.tolist()


def test_landmarks_found_in_some_frames_or_none(back) -> None:
    _image, surface, truth = back
    document = _analysis(
        ("a.png", truth_backshape(truth, surface, drop=("DL",))),
        ("b.png", truth_backshape(truth, surface, shift=(0.0, 4.0, 0.0), drop=("DL", "SP"))),
    ).document()
    reasons = {r["what"]: r["why"] for r in document["reasons"]}
    assert document["landmarks"]["DL"] is None and reasons["DL"] == "arms over the dimples"
    assert document["landmarks"]["SP"] == pytest.approx(list(truth["landmarks"]["SP"]))
    assert reasons["SP"] == "found in 1 of 2 frames"
    dr = np.asarray(truth["landmarks"]["DR"]) + np.array([0.0, 2.0, 0.0])
    assert document["landmarks"]["DR"] == pytest.approx(list(dr))


def test_document_is_strict_json_in_the_world_frame(back) -> None:
    _image, surface, truth = back
    document = _analysis(("frame.png", truth_backshape(truth, surface, drop=("SP",)))).document()
    text = json.dumps(document, allow_nan=False)  # no NaN reaches a client
    assert json.loads(text) == document
    assert document["format"] == "rasterserver.back-shape/1"
    assert document["frame"]["unit"] == "mm"
    assert document["frame"]["gravity"] == [0.0, 1.0, 0.0]
    assert "world" in document["frame"]["name"] and "Y down" in document["frame"]["axes"]
    assert list(document["landmarks"]) == list(LANDMARKS)
    for name in ("VP", "DL", "DR", "DM"):
        assert document["landmarks"][name] == pytest.approx(list(truth["landmarks"][name]))
    assert document["landmarks"]["SP"] is None
    assert document["sagittal_points"] == dict.fromkeys(("ICT", "KA", "ITL", "LA", "ILS"))
    assert document["landmark_confidence"]["SP"] == 0.0
    assert document["reasons"] == [{"what": "SP", "why": "image cropped"}]
    for name, entry in document["parameters"].items():
        assert set(entry) == {"value", "unit", "spread"}, name
        assert entry["unit"] in ("mm", "deg") and entry["spread"] is None
        assert math.isfinite(entry["value"])
    assert list(document["parameters"]) == ordered_parameters(document["parameters"])
    axes = np.array(list(document["body_frame"]["axes"].values()))
    np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-9)
    assert document["frames"] == [
        {"name": "frame.png", "index": None, "analysed": True, "reason": ""}
    ]
    assert document["plugin"]["plugin"] == "analysis.back-shape"


def test_document_of_several_frames_names_the_refused_ones(back) -> None:
    _image, surface, truth = back
    analysis = _analysis(
        ("a.png", truth_backshape(truth, surface)),
        ("b.png", BackShape.empty("no back in view")),
        ("c.png", truth_backshape(truth, surface, scale=1.02)),
    )
    document = analysis.check().document()
    assert {"what": "b.png", "why": "no back in view"} in document["reasons"]
    assert [f["analysed"] for f in document["frames"]] == [True, False, True]
    assert document["parameters"]["trunk_length"]["spread"] > 0
    assert analysis.shown_frame().name == "a.png"


def test_an_empty_analysis_is_refused_with_its_reason() -> None:
    empty = BackShape.empty(
        "the calibration gives no direction of gravity", reasons={"VP": "not searched"}
    )
    analysis = _analysis(("frame.png", empty))
    assert analysis.refused
    with pytest.raises(AnalysisRefusedError, match=r"frame\.png: the calibration gives no") as err:
        analysis.check()
    assert "VP: not searched" in str(err.value)
    assert err.value.exit_code == 2 and err.value.http_status == 422
    several = _analysis(("a.png", empty), ("b.png", BackShape.empty("no back in view")))
    with pytest.raises(AnalysisRefusedError, match=r"a\.png: .*gravity; b\.png: no back in view"):
        several.check()


def test_labels_and_key_parameters() -> None:
    assert parameter_label("trunk_length") == "Trunk length VP-DM"
    assert parameter_label("something_new") == "something_new"
    assert ordered_parameters(["zeta", "trunk_length", "alpha"]) == [
        "trunk_length",
        "alpha",
        "zeta",
    ]
    assert len(set(KEY_PARAMETERS)) == len(KEY_PARAMETERS)


def test_analyse_frames_refuses_degenerate_input(back) -> None:
    image, _surface, _truth = back
    station = default_station()
    raster = station.raster_definition
    with pytest.raises(InputError, match="no frame"):
        analyse_frames([], calibration=station, raster=raster)
    with pytest.raises(InputError, match=r"small\.png: the frame is 302x288"):
        analyse_frames([("small.png", image[::2, ::2])], calibration=station, raster=raster)
    # nothing in view: no surface, so nothing to analyse
    black = analyse_frames(
        [("black.png", np.zeros_like(image))], calibration=station, raster=raster
    )
    assert black.refused and black.frames[0].surface is not None
    with pytest.raises(AnalysisRefusedError, match=r"black\.png"):
        black.check()


def test_analyse_frames_runs_the_chain_per_frame(back) -> None:
    image, _surface, _truth = back
    station = default_station()
    analysis = analyse_frames(
        [("a.png", image), ("b.png", image)], calibration=station, raster=station.raster_definition
    )
    assert [f.name for f in analysis.frames] == ["a.png", "b.png"]
    assert all(f.surface is not None and f.surface.valid.sum() > 1000 for f in analysis.frames)
    assert analysis.plugin["plugin"] == "analysis.back-shape"
    assert analysis.calibration == station.name


def test_archived_analysis_is_read_and_processed_on_request(settings: Settings, back) -> None:
    image, _surface, _truth = back
    station = default_station()
    with Archive.create(settings) as archive:
        archive.add_patient("P-ANALYSIS")
        register_station(archive, station, "clinic-a")
        second = np.clip(image.astype(np.int16) + 1, 0, 255).astype(np.uint8)
        acq = archive.ingest(
            [
                FrameSource(image, role="raster", name="a.npy"),
                FrameSource(second, role="raster", name="b.npy"),
                FrameSource(np.zeros_like(image), role="dark", name="dark.npy"),
            ],
            patient="P-ANALYSIS",
            station="clinic-a",
        )
        dark = archive.ingest(
            [FrameSource(np.zeros_like(image), role="dark", name="d.npy")],
            patient="P-ANALYSIS",
            station="clinic-a",
        )
        pipeline = Pipeline(archive)
        with pytest.raises(NotFoundError, match="no stored analysis yet: process it"):
            acquisition_analysis(pipeline, acq.uid)
        with pytest.raises(NotFoundError, match="unknown acquisition"):
            acquisition_analysis(pipeline, "f" * 32)
        with pytest.raises(InputError, match="no raster frame"):
            acquisition_analysis(pipeline, dark.uid, process=True)
        analysis = acquisition_analysis(pipeline, acq.uid, process=True, surfaces=True)
        # every raster frame analysed and stored, with provenance; the dark frame left alone
        assert [f.index for f in analysis.frames] == [0, 1]
        rows = [r for r in pipeline.results(acq.uid) if r.stage == "analysis"]
        assert sorted(r.frame_index for r in rows) == [0, 1]
        assert all(
            f.result is not None and f.result.plugin == "analysis.back-shape"
            for f in analysis.frames
        )
        assert all(f.surface is not None and f.surface.valid.sum() > 1000 for f in analysis.frames)
        assert analysis.uid == acq.uid and analysis.calibration == "clinic-a:1"
        assert analysis.gravity == [0.0, 1.0, 0.0]
        # stored now: read without processing, nothing recomputed
        again = acquisition_analysis(pipeline, acq.uid, process=True)
        assert [f.result.id for f in again.frames] == [f.result.id for f in analysis.frames]
        assert len(pipeline.results(acq.uid)) == len(rows) + 2 * 6
        document = again.document()
        for frame in document["frames"]:
            provenance = frame["provenance"]
            assert provenance["stage"] == "analysis"
            assert provenance["plugin"] == "analysis.back-shape"
            assert len(provenance["output_checksum"]) == 64
            assert provenance["created_at"].endswith("Z")
        json.dumps(document, allow_nan=False)


def test_parameter_columns_one_column_per_visit() -> None:
    visit = {
        "trunk_length": {"value": 430.46, "unit": "mm", "spread": None},
        "scoliosis_angle_deg": {"value": -0.04, "unit": "deg", "spread": None},
        "not_a_key_parameter": {"value": 1.0, "unit": "mm", "spread": None},
    }
    lines = parameter_columns([("visit 1", visit), ("visit 2", None)])
    assert [line.split() for line in lines] == [
        ["parameter", "visit", "1", "visit", "2", "unit"],
        ["Trunk", "length", "VP-DM", "430.5", "-", "mm"],
        ["Scoliosis", "angle", "0.0", "-", "deg"],  # never "-0.0"
    ]
    assert parameter_columns([("visit 1", None)]) == ["parameter   visit 1  unit"]
