"""The calibration and raster documents: every broken one refused naming the field, good ones
accepted unchanged, files read without tracebacks, and the docs' tables equal to the models."""

from __future__ import annotations

import copy
import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rasterserver.documents import (
    MAX_DOCUMENT_BYTES,
    CalibrationDocument,
    RasterDocument,
    calibration_from_document,
    device_from_document,
    fill_format_tables,
    load_calibration_document,
    load_raster_document,
    raster_from_document,
    read_document,
)
from rasterserver.errors import InputError
from rasterserver.optics import Station, default_station, rotation_matrix
from rasterserver.raster import default_raster, make_raster

DOCS = Path(__file__).resolve().parents[1] / "docs" / "formats.md"


def good_calibration() -> dict[str, Any]:
    """The default station's calibration document."""
    return default_station().to_dict()


def good_raster() -> dict[str, Any]:
    """The default raster definition."""
    return default_raster().to_dict()


def _changed(base: Callable[[], dict[str, Any]], change: Callable[[dict[str, Any]], Any]):
    document = copy.deepcopy(base())
    change(document)
    return document


def cal(change: Callable[[dict[str, Any]], Any]) -> dict[str, Any]:
    """The good calibration with ``change`` applied."""
    return _changed(good_calibration, change)


def ras(change: Callable[[dict[str, Any]], Any]) -> dict[str, Any]:
    """The good raster definition with ``change`` applied."""
    return _changed(good_raster, change)


def _set(part: str | None, key: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def change(d: dict[str, Any]) -> None:
        (d[part] if part else d)[key] = value

    return change


def _drop(part: str | None, key: str) -> Callable[[dict[str, Any]], None]:
    def change(d: dict[str, Any]) -> None:
        del (d[part] if part else d)[key]

    return change


def _line(i: int, key: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def change(d: dict[str, Any]) -> None:
        d["lines"][i][key] = value

    return change


def _zero_base(d: dict[str, Any]) -> None:
    d["projector"]["t"] = [0.0, 0.0, 2000.0]
    d["projector"].pop("centre")


def _base_along_lines(d: dict[str, Any]) -> None:
    # the projector 800 mm to the side: along its x axis, the direction of the raster lines
    d["projector"]["t"] = [-800.0, 0.0, 2000.0]
    d["projector"].pop("centre")


# (id, document, field named in the message, words of the message)
BROKEN_CALIBRATIONS = [
    ("K-all-zeros", cal(_set("camera", "K", [[0, 0, 0]] * 3)), "camera.K", "focal lengths"),
    ("K-missing", cal(_drop("camera", "K")), "camera.K", "missing"),
    ("projector-missing", cal(_drop(None, "projector")), "projector", "missing"),
    ("camera-missing", cal(_drop(None, "camera")), "camera", "missing"),
    ("foreign-format", cal(_set(None, "format", "opencv/1")), "format", "'opencv/1'"),
    ("format-missing", cal(_drop(None, "format")), "format", "looks like a calibration"),
    (
        "R-not-orthonormal",
        cal(_set("camera", "R", [[1, 0.1, 0], [0, 1, 0], [0, 0, 1]])),
        "camera.R",
        "not a rotation",
    ),
    (
        "R-reflection",
        cal(_set("projector", "R", [[1, 0, 0], [0, 1, 0], [0, 0, -1]])),
        "projector.R",
        "reflection",
    ),
    ("negative-width", cal(_set("camera", "width", -576)), "camera.width", "greater than"),
    ("zero-width", cal(_set("projector", "width", 0.0)), "projector.width", "greater than"),
    ("fractional-width", cal(_set("camera", "width", 576.5)), "camera.width", "integer"),
    ("width-as-text", cal(_set("camera", "height", "604")), "camera.height", "integer"),
    ("zero-baseline", cal(_zero_base), "projector.t", "stereo base"),
    ("baseline-along-the-lines", cal(_base_along_lines), "projector.t", "across the raster"),
    (
        "singular-K",
        cal(_set("camera", "K", [[2000, 0, 300], [0, 0, 300], [0, 0, 1]])),
        "camera.K",
        "fy = 0",
    ),
    (
        "negative-focal",
        cal(_set("projector", "K", [[-2000, 0, 500], [0, 2000, -300], [0, 0, 1]])),
        "projector.K",
        "focal lengths must be positive",
    ),
    (
        "K-lower-triangle",
        cal(_set("camera", "K", [[2000, 0, 300], [3, 2000, 300], [0, 0, 1]])),
        "camera.K",
        "upper triangular",
    ),
    (
        "K-last-row",
        cal(_set("camera", "K", [[2000, 0, 300], [0, 2000, 300], [0, 0, 2]])),
        "camera.K",
        "[0, 0, 1]",
    ),
    ("K-2x3", cal(_set("camera", "K", [[2000, 0, 300], [0, 2000, 300]])), "camera.K", "at least 3"),
    (
        "NaN-in-K",
        cal(lambda d: d["camera"]["K"][0].__setitem__(0, math.nan)),
        "camera.K[0][0]",
        "finite",
    ),
    (
        "Inf-in-t",
        cal(lambda d: d["projector"]["t"].__setitem__(1, math.inf)),
        "projector.t[1]",
        "finite",
    ),
    (
        "huge-number",
        cal(lambda d: d["camera"]["R"][0].__setitem__(0, 1e308)),
        "camera.R[0][0]",
        "beyond",
    ),
    (
        "distortion-3",
        cal(_set("camera", "distortion", [0.0, 0.0, 0.0])),
        "camera.distortion",
        "at least 4",
    ),
    (
        "distortion-6",
        cal(_set("camera", "distortion", [0.0] * 6)),
        "camera.distortion",
        "4, 5, 8, 12 or 14",
    ),
    (
        "distortion-beyond-k3",
        cal(_set("camera", "distortion", [0.0] * 5 + [0.1, 0.0, 0.0])),
        "camera.distortion",
        "must be 0",
    ),
    (
        "distortion-NaN",
        cal(_set("camera", "distortion", [math.nan, 0, 0, 0, 0])),
        "camera.distortion[0]",
        "finite",
    ),
    (
        "distortion-folds",
        cal(_set("camera", "distortion", [-50.0, 0, 0, 0, 0])),
        "camera.distortion",
        "not invertible",
    ),
    (
        "misspelt-field",
        cal(_set("camera", "distorsion", [0.0] * 5)),
        "camera.distorsion",
        "unknown field",
    ),
    (
        "stale-centre",
        cal(_set("camera", "centre", [0.0, 0.0, -1000.0])),
        "camera.centre",
        "-R.T @ t",
    ),
    ("unknown-model", cal(_set("camera", "model", "fisheye")), "camera.model", "opencv-pinhole"),
    ("metres", cal(_set(None, "units", "m")), "units", "'mm'"),
    ("gravity-not-unit", cal(_set(None, "gravity", [0.0, 2.0, 0.0])), "gravity", "unit vector"),
    ("gravity-zero", cal(_set(None, "gravity", [0.0, 0.0, 0.0])), "gravity", "length is 0"),
    ("gravity-NaN", cal(_set(None, "gravity", [0.0, math.nan, 0.0])), "gravity[1]", "finite"),
    ("gravity-2d", cal(_set(None, "gravity", [0.0, 1.0])), "gravity", "at least 3"),
    ("raster-name-empty", cal(_set(None, "raster", "")), "raster", "at least 1"),
    ("raster-name-number", cal(_set(None, "raster", 7)), "raster", "string"),
    (
        "inline-raster-broken",
        cal(_set(None, "raster", ras(_line(2, "kind", "bold")))),
        "raster.lines[2].kind",
        "'light' or 'heavy'",
    ),
    ("camera-is-a-list", cal(_set(None, "camera", [1, 2, 3])), "camera", "object"),
    ("a-raster-definition", good_raster(), "raster definition", "not a calibration"),
    ("an-array", [good_calibration()], "array", "JSON object"),
    ("a-number", 3, "number", "JSON object"),
    ("empty-object", {}, "format", "missing"),
]


def _window_too_short(d: dict[str, Any]) -> None:
    d["code"]["window"] = 4


BROKEN_RASTERS = [
    ("a-1", {"a": 1}, "format", "missing"),
    ("a-calibration", good_calibration(), "calibration", "not a raster definition"),
    (
        "foreign-format",
        ras(_set(None, "format", "rasterserver.raster/2")),
        "format",
        "rasterserver.raster/2",
    ),
    ("lines-missing", ras(_drop(None, "lines")), "lines", "missing"),
    ("no-lines", ras(_set(None, "lines", [])), "lines", "at least 1"),
    ("code-missing", ras(_drop(None, "code")), "code", "missing"),
    ("name-missing", ras(_drop(None, "name")), "name", "missing"),
    ("v-decreasing", ras(_line(3, "v", 0.0)), "lines[3].v", "strictly increasing"),
    ("v-repeated", ras(_line(3, "v", 74.5)), "lines[3].v", "strictly increasing"),
    ("number-twice", ras(_line(3, "number", 1)), "lines[3].number", "lines[0]"),
    ("kind-unknown", ras(_line(3, "kind", "bold")), "lines[3].kind", "'light' or 'heavy'"),
    ("width-zero", ras(_line(3, "width", 0)), "lines[3].width", "greater than 0"),
    ("v-NaN", ras(_line(3, "v", math.nan)), "lines[3].v", "finite"),
    ("v-infinite", ras(_line(3, "v", -math.inf)), "lines[3].v", "finite"),
    ("number-fractional", ras(_line(3, "number", 4.5)), "lines[3].number", "integer"),
    ("line-field-unknown", ras(_line(3, "colour", "red")), "lines[3].colour", "unknown field"),
    (
        "window-longer-than-raster",
        ras(lambda d: d["code"].__setitem__("window", 91)),
        "code.window",
        "longer than the raster",
    ),
    (
        "window-zero",
        ras(lambda d: d["code"].__setitem__("window", 0)),
        "code.window",
        "greater than or equal to 1",
    ),
    ("code-does-not-identify", ras(_window_too_short), "code", "identical"),
    (
        "min-distance-not-met",
        ras(lambda d: d["code"].__setitem__("min_distance", 3)),
        "code",
        "differ in only 2",
    ),
    (
        "min-distance-over-window",
        ras(lambda d: d["code"].update(window=2, min_distance=3)),
        "code.min_distance",
        "exceeds the window",
    ),
    ("an-array", [good_raster()], "array", "JSON object"),
]


@pytest.mark.parametrize(
    ("document", "field", "words"),
    [c[1:] for c in BROKEN_CALIBRATIONS],
    ids=[c[0] for c in BROKEN_CALIBRATIONS],
)
def test_broken_calibrations_are_refused_naming_the_field(document, field, words) -> None:
    with pytest.raises(InputError) as refused:
        calibration_from_document(document, source="cal.json")
    message = str(refused.value)
    assert message.startswith("cal.json: ")
    assert field in message and words in message, message


@pytest.mark.parametrize(
    ("document", "field", "words"),
    [c[1:] for c in BROKEN_RASTERS],
    ids=[c[0] for c in BROKEN_RASTERS],
)
def test_broken_rasters_are_refused_naming_the_field(document, field, words) -> None:
    with pytest.raises(InputError) as refused:
        raster_from_document(document, source="raster.json")
    message = str(refused.value)
    assert message.startswith("raster.json: ")
    assert field in message and words in message, message


def test_the_issue_reports_fourteen_broken_calibrations_the_table_holds_more() -> None:
    assert len(BROKEN_CALIBRATIONS) >= 14 and len(BROKEN_RASTERS) >= 14


def _same_station(a: Station, b: Station) -> None:
    for da, db in ((a.camera, b.camera), (a.projector, b.projector)):
        for attr in ("K", "dist", "R", "t"):
            np.testing.assert_array_equal(getattr(da, attr), getattr(db, attr))
        assert (da.width, da.height) == (db.width, db.height)


@pytest.mark.parametrize(
    "station",
    [
        default_station(),
        default_station(2048, 2448, raster=default_raster(), name="inline raster"),
        default_station(camera_distortion=(0.0,) * 5, projector_distortion=(0.0,) * 5),
        Station(default_station().camera, default_station().projector, name="no gravity"),
    ],
    ids=["default", "inline-raster", "no-distortion", "no-gravity"],
)
def test_good_calibrations_round_trip_exactly(station: Station) -> None:
    document = station.to_dict()
    back = calibration_from_document(document)
    _same_station(back, station)
    assert back.name == station.name
    assert back.to_dict() == document
    if station.gravity is None:
        assert back.gravity is None and "gravity" not in document


def test_gravity_round_trips_and_the_default_station_knows_the_vertical(tmp_path: Path) -> None:
    station = default_station()
    assert station.gravity is not None and station.gravity.tolist() == [0.0, 1.0, 0.0]
    tilted = np.array([0.0, math.cos(0.1), math.sin(0.1)])
    other = Station(station.camera, station.projector, gravity=tilted)
    assert other.to_dict()["gravity"] == tilted.tolist()
    back = load_calibration_document(Path(other.save(tmp_path / "calibration.json")))
    assert back.gravity is not None
    np.testing.assert_array_equal(back.gravity, tilted)
    with pytest.raises(ValueError, match="unit vector"):
        Station(station.camera, station.projector, gravity=np.array([0.0, 2.0, 0.0]))


def test_tolerated_variants_are_accepted() -> None:
    # rotations written with six decimals, OpenCV's 4 and 8 coefficients, no centre, no raster
    rx = rotation_matrix(rx_deg=12.0)
    rounded = np.round(rx, 6)
    document = cal(_set("projector", "R", rounded.tolist()))
    document["projector"]["t"] = (-rounded @ np.array([0.0, -800.0, -2000.0])).tolist()
    document["projector"].pop("centre")
    document["camera"]["distortion"] = [-0.05, 0.0, 0.0, 0.0]
    document["projector"]["distortion"] = [-0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    del document["raster"], document["units"], document["conventions"]
    station = calibration_from_document(document)
    # the nearest rotation is used: a proper one, within the rounding of the given matrix
    r = station.projector.R
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r, rounded, atol=1e-6)
    assert station.camera.dist.tolist() == [-0.05, 0.0, 0.0, 0.0, 0.0]
    assert station.raster == "default"


def test_good_rasters_are_accepted() -> None:
    for raster in (default_raster(), make_raster(30, window=7, min_distance=2, name="small")):
        back = raster_from_document(raster.to_dict())
        np.testing.assert_array_equal(back.positions, raster.positions)
        assert back.kinds == raster.kinds and back.window == raster.window
    one = {
        "format": "rasterserver.raster/1",
        "name": "one",
        "code": {"window": 1},
        "lines": [{"number": 7, "v": 3.0, "kind": "heavy", "width": 1.0}],
    }
    assert raster_from_document(one).n_lines == 1


def test_many_problems_are_listed_at_most_five() -> None:
    document = cal(
        lambda d: d["camera"].update(
            K=None, R=None, t=None, width=None, height=None, distortion=None
        )
    )
    with pytest.raises(InputError) as refused:
        calibration_from_document(document)
    message = str(refused.value)
    assert message.count(";") == 4 and "(and 1 more)" in message


# --- reading files and bytes --------------------------------------------------------------


def _write(tmp_path: Path, name: str, data: bytes | str) -> Path:
    path = tmp_path / name
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return path


UNREADABLE = [
    ("missing", None, "no such calibration file"),
    ("directory", "dir", "is a directory"),
    ("empty", b"", "empty"),
    ("whitespace", b" \n\t", "empty"),
    ("binary", b"\x89PNG\r\n\x1a\n\x00\x00", "not UTF-8"),
    ("latin-1", '{"name": "Müller"}'.encode("latin-1"), "not UTF-8"),
    ("not-json", b"camera: {K: 1}", "not a JSON calibration"),
    ("truncated", json.dumps(good_calibration())[:200].encode(), "not a JSON calibration"),
    ("deeply-nested", b"[" * 200_000 + b"]" * 200_000, "nested too deeply"),
    ("deeply-nested-objects", b'{"a":' * 100_000 + b"1" + b"}" * 100_000, "nested too deeply"),
    (
        "duplicate-key",
        b'{"format": "rasterserver.calibration/1", "format": "x"}',
        "'format' appears twice",
    ),
    ("too-large", b" " * (MAX_DOCUMENT_BYTES + 1), "too large"),
    ("an-array", b"[1, 2, 3]", "this is an array"),
    ("a-string", b'"calibration"', "this is a string"),
    ("null", b"null", "this is null"),
    ("NaN-top-level", b"NaN", "this is a number"),
]


@pytest.mark.parametrize(
    ("data", "words"), [c[1:] for c in UNREADABLE], ids=[c[0] for c in UNREADABLE]
)
def test_unreadable_calibration_files_are_a_sentence(tmp_path, data, words) -> None:
    if data is None:
        path = tmp_path / "none.json"
    elif data == "dir":
        path = tmp_path / "calibration.json"
        path.mkdir()
    else:
        path = _write(tmp_path, "c.json", data)
    with pytest.raises(InputError, match=words) as refused:
        load_calibration_document(path)
    assert str(refused.value).startswith(path.name)


def test_a_byte_order_mark_and_nan_text_are_handled(tmp_path: Path) -> None:
    text = json.dumps(good_calibration())
    bom = _write(tmp_path, "bom.json", b"\xef\xbb\xbf" + text.encode())
    station = load_calibration_document(bom)
    assert station.camera.width == 576
    # Python's json reads NaN; the document is refused where it stands
    with_nan = text.replace('"distortion": [-0.05', '"distortion": [NaN', 1)
    with pytest.raises(InputError, match=r"camera\.distortion\[0\]: must be a finite number"):
        load_calibration_document(with_nan)
    with pytest.raises(InputError, match=r"lines\[0\]\.v: must be a finite number"):
        load_raster_document(default_raster().to_json().replace('"v": 54.5', '"v": Infinity'))


def test_loaders_accept_paths_bytes_and_text(tmp_path: Path) -> None:
    path = default_station().save(tmp_path / "calibration.json")
    for data in (path, path.read_bytes(), path.read_text()):
        assert load_calibration_document(data).camera.shape == (604, 576)
    raster_path = default_raster().save(tmp_path / "raster.json")
    assert load_raster_document(Path(raster_path)).n_lines == 90
    assert load_raster_document(raster_path.read_bytes()).n_lines == 90
    with pytest.raises(InputError, match=r"raster\.json: this is a raster definition"):
        load_calibration_document(raster_path)
    with pytest.raises(InputError, match=r"calibration\.json: this is a calibration"):
        load_raster_document(Path(path))
    assert read_document(b"{}", what="x") == {}


# --- the schema and the documentation ----------------------------------------------------


def test_the_json_schema_describes_the_checks() -> None:
    schema = CalibrationDocument.model_json_schema()
    assert schema["required"] == ["format", "camera", "projector"]
    assert schema["properties"]["format"]["const"] == "rasterserver.calibration/1"
    assert schema["additionalProperties"] is False
    camera = schema["$defs"]["CameraDocument"]
    assert camera["properties"]["width"]["minimum"] == 1
    assert camera["properties"]["K"]["minItems"] == 3
    raster = RasterDocument.model_json_schema()
    assert raster["$defs"]["RasterLine"]["properties"]["kind"]["enum"] == ["light", "heavy"]


def test_docs_tables_are_generated_from_the_models() -> None:
    text = DOCS.read_text(encoding="utf-8")
    expected = fill_format_tables(text)
    if expected != text and os.environ.get("RASTERSERVER_UPDATE_DOCS"):
        DOCS.write_text(expected, encoding="utf-8")
        text = expected
    assert text.count("<!-- generated from rasterserver.documents.format_tables()") == 5
    assert expected == text, (
        "docs/formats.md differs from the document models: run RASTERSERVER_UPDATE_DOCS=1 "
        ".venv/bin/pytest tests/test_documents.py -k docs_tables"
    )


def test_devices_read_alone_go_through_the_same_checks() -> None:
    from rasterserver.optics import Camera, Projector

    station = default_station()
    camera = device_from_document(Camera, station.camera.to_dict(), source="camera")
    assert isinstance(camera, Camera) and camera.shape == (604, 576)
    projector = device_from_document(Projector, station.projector.to_dict(), source="projector")
    assert isinstance(projector, Projector)
    broken = station.camera.to_dict() | {"K": [[0.0] * 3] * 3}
    with pytest.raises(InputError, match=r"^camera: K: focal lengths must be positive"):
        device_from_document(Camera, broken, source="camera")


SCHEMAS = DOCS.parent / "schemas"


def test_schema_files_are_generated_from_the_models() -> None:
    from rasterserver.documents import json_schemas, write_json_schemas

    expected = json_schemas()
    if os.environ.get("RASTERSERVER_UPDATE_DOCS"):
        write_json_schemas(SCHEMAS)
    assert sorted(p.name for p in SCHEMAS.glob("*.json")) == sorted(expected)
    for name, text in expected.items():
        assert (SCHEMAS / name).read_text(encoding="utf-8") == text, (
            f"docs/schemas/{name} differs from the document models: run "
            "RASTERSERVER_UPDATE_DOCS=1 .venv/bin/pytest tests/test_documents.py -k schema_files"
        )
        schema = json.loads(text)
        assert schema["$schema"].endswith("/2020-12/schema") and schema["type"] == "object"


def test_schema_files_accept_the_good_documents() -> None:
    """The published schema is the models' own: the good documents satisfy its required
    fields, and a document's keys are all among its properties."""
    for name, document in (
        ("calibration.schema.json", good_calibration()),
        ("raster.schema.json", good_raster()),
    ):
        schema = json.loads((SCHEMAS / name).read_text(encoding="utf-8"))
        assert set(schema["required"]) <= set(document) <= set(schema["properties"])


def test_stored_calibration_names_the_row() -> None:
    from rasterserver.documents import stored_calibration

    station = stored_calibration(good_calibration(), label="clinic-1:2")
    assert isinstance(station, Station)
    broken = good_calibration() | {"camera": good_calibration()["camera"] | {"width": 0}}
    with pytest.raises(InputError, match=r"^calibration clinic-1:2: camera\.width: "):
        stored_calibration(broken, label="clinic-1:2")


def test_calibration_raster_from_a_file_a_row_or_the_station(tmp_path: Path) -> None:
    from rasterserver.documents import calibration_raster

    station = default_station()
    assert calibration_raster(station, source="cal.json").name == station.raster_definition.name
    other = make_raster(name="other", n_lines=40)
    path = tmp_path / "raster.json"
    path.write_text(json.dumps(other.to_dict()), encoding="utf-8")
    assert calibration_raster(station, path, source="cal.json").name == "other"
    assert calibration_raster(station, other.to_dict(), source="x").name == "other"
    with pytest.raises(InputError, match=r"^the raster of calibration s:1: "):
        calibration_raster(station, {"format": "rasterserver.raster/1"}, source="calibration s:1")
    unknown = Station(station.camera, station.projector, raster="no-such-raster")
    with pytest.raises(
        InputError, match=r"^cal\.json: unknown built-in raster 'no-such-raster'.*; give it$"
    ):
        calibration_raster(unknown, source="cal.json", hint="; give it")
