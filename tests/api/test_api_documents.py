"""Calibrations, rasters and frame sizes over HTTP, on a live server: a refused document or a
frame that cannot fit its calibration is a 4xx naming the field or both sizes, and nothing is
stored; an upload no calibration applies to says why in ``warnings``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from api_helpers import PATIENT_ID, LiveServer, npy_bytes
from test_documents import BROKEN_CALIBRATIONS, BROKEN_RASTERS, good_calibration, good_raster

# the cases the issue found accepted over HTTP, and a few more of each kind
HTTP_CALIBRATIONS = [
    "singular-K",
    "camera-missing",
    "K-all-zeros",
    "zero-baseline",
    "NaN-in-K",
    "a-raster-definition",
    "misspelt-field",
    "gravity-not-unit",
]
HTTP_RASTERS = ["a-1", "a-calibration", "v-decreasing", "code-does-not-identify", "v-NaN"]


def _case(name: str, table: list) -> tuple:
    return next(c[1:] for c in table if c[0] == name)


def _post(client, url: str, body: dict):
    # NaN as Python's json writes it: the server reads it, the checks refuse it
    return client.post(
        url, content=json.dumps(body, allow_nan=True), headers={"content-type": "application/json"}
    )


def test_broken_documents_are_422_naming_the_field_and_nothing_is_stored(
    live: LiveServer,
) -> None:
    with live.client("admin") as admin:
        for name in HTTP_CALIBRATIONS:
            document, field, words = _case(name, BROKEN_CALIBRATIONS)
            r = _post(admin, "/stations/clinic-1/calibrations", {"parameters": document})
            assert r.status_code == 422, (name, r.text)
            body = r.json()
            assert body["error"] == "InputError"
            assert body["detail"].startswith("parameters: ") and field in body["detail"]
            assert words in body["detail"], (name, body)
        for name in HTTP_RASTERS:
            document, field, words = _case(name, BROKEN_RASTERS)
            r = _post(admin, "/rasters", {"name": "r1", "definition": document})
            assert r.status_code == 422, (name, r.text)
            detail = r.json()["detail"]
            assert detail.startswith("definition: ") and field in detail and words in detail
        assert admin.get("/stations/clinic-1/calibrations").json() == []
        assert admin.get("/rasters/r1").status_code == 404


@pytest.mark.parametrize(
    "body",
    [
        {"parameters": [good_calibration()]},
        {"parameters": "rasterserver.calibration/1"},
        {"parameters": None},
    ],
    ids=["array", "string", "null"],
)
def test_a_calibration_that_is_not_an_object_is_422(live_sqlite: LiveServer, body) -> None:
    with live_sqlite.client("admin") as admin:
        r = admin.post("/stations/clinic-1/calibrations", json=body)
        assert r.status_code == 422 and r.json()["error"] == "ValidationError"
        assert admin.get("/stations/clinic-1/calibrations").json() == []


def test_deeply_nested_documents_are_refused_not_a_500(live_sqlite: LiveServer) -> None:
    deep = "[" * 100_000 + "]" * 100_000
    with live_sqlite.client("admin") as admin:
        for url, body in (
            ("/rasters", f'{{"name": "r", "definition": {deep}}}'),
            ("/stations/clinic-1/calibrations", f'{{"parameters": {deep}}}'),
        ):
            r = admin.post(url, content=body, headers={"content-type": "application/json"})
            assert r.status_code in (400, 422), r.text
        nested = {
            "format": "rasterserver.raster/1",
            "name": "x",
            "description": "",
            "code": {"window": 1},
            "lines": [],
            "extra": json.loads("[" * 500 + "]" * 500),
        }
        r = admin.post("/rasters", json={"name": "r", "definition": nested})
        assert r.status_code == 422 and "unknown field" in r.json()["detail"]


def test_good_documents_are_stored(live_sqlite: LiveServer) -> None:
    with live_sqlite.client("admin") as admin:
        r = admin.post("/rasters", json={"name": "default", "definition": good_raster()})
        assert r.status_code == 201, r.text
        cal = good_calibration()
        r = admin.post(
            "/stations/clinic-1/calibrations", json={"parameters": cal, "raster": "default"}
        )
        assert r.status_code == 201, r.text
        assert r.json()["parameters"] == cal and r.json()["parameters"]["gravity"] == [0, 1, 0]


def test_the_documents_schema_is_published(live_sqlite: LiveServer) -> None:
    with live_sqlite.client() as anyone:
        document = anyone.get("/openapi.json").json()
    schemas = document["components"]["schemas"]
    parameters = schemas["CalibrationIn"]["properties"]["parameters"]
    assert parameters["$ref"].endswith("/CalibrationDocument")
    assert schemas["CalibrationDocument"]["required"] == ["format", "camera", "projector"]
    assert schemas["RasterIn"]["properties"]["definition"]["$ref"].endswith("/RasterDocument")
    assert "warnings" in schemas["UploadOut"]["properties"]


def _upload(client, shape: tuple[int, int], **data: str):
    pixels = np.full(shape, 9, np.uint8)
    return client.post(
        "/acquisitions",
        files=[("files", ("frame.npy", npy_bytes(pixels)))],
        data={"patient": PATIENT_ID, **data},
    )


def test_frames_that_cannot_fit_the_calibration_are_refused(live: LiveServer) -> None:
    with live.client("admin") as admin:
        assert (
            admin.post(
                "/stations/clinic-1/calibrations", json={"parameters": good_calibration()}
            ).status_code
            == 201
        )
        assert admin.post("/stations", json={"name": "bare-1"}).status_code == 201
    with live.client("station") as cam:
        for shape in ((300, 400), (1, 1), (576, 604)):
            r = _upload(cam, shape, station="clinic-1")
            assert r.status_code == 422, r.text
            detail = r.json()["detail"]
            assert f"{shape[0]}x{shape[1]}" in detail and "604x576" in detail
        fits = _upload(cam, (604, 576), station="clinic-1")
        assert fits.status_code == 201 and fits.json()["warnings"] == []
        bare = _upload(cam, (300, 400), station="bare-1")
        assert bare.status_code == 201
        assert bare.json()["warnings"] == [
            "station 'bare-1' has no calibration yet, so none applies: the frame size was not "
            "checked; store one (`rasterserver station add-calibration` or `rasterserver "
            "calibrate`), then process with --calibration bare-1:VERSION"
        ]
        loose = _upload(cam, (300, 400))
        assert "no station given" in loose.json()["warnings"][0]
    with live.client("clinician") as c:
        stored = c.get("/acquisitions").json()
    # only the three accepted uploads, the refused ones left nothing
    assert len(stored) == 3
    assert sorted((a["frames"][0]["height"], a["frames"][0]["width"]) for a in stored) == [
        (300, 400),
        (300, 400),
        (604, 576),
    ]
