"""The back-shape analysis over HTTP, on a live server (SQLite and PostgreSQL): a stored
analysis for clinicians, the same pseudonymised for researchers, the report PNG/PDF, the
answers without an analysis or with an empty one, and the audit trail of every read."""

from __future__ import annotations

import datetime as dt

import cv2
import httpx
import numpy as np
import pytest
from api_helpers import PATIENT_ID, PATIENT_NAME, LiveServer, npy_bytes, run_job
from backshape_truth import simulated

from rasterserver.optics import default_station
from rasterserver.records_analysis import LANDMARKS
from rasterserver.services.audit_trail import audit_events
from rasterserver.services.pseudonyms import Pseudonymiser

ACQUIRED = "2025-03-01T10:15:00+01:00"
TRUE_TIME = dt.datetime(2025, 3, 1, 9, 15, tzinfo=dt.UTC)


@pytest.fixture(scope="module")
def back_frame() -> np.ndarray:
    """A simulated moderate scoliosis as the default station sees it (seconds: once)."""
    return simulated("moderate")[0]


def _calibrate(live: LiveServer) -> None:
    station = default_station()
    with live.client("admin") as admin:
        raster = admin.post(
            "/rasters", json={"name": "default", "definition": station.raster_definition.to_dict()}
        )
        assert raster.status_code == 201, raster.text
        calibration = admin.post(
            "/stations/clinic-1/calibrations",
            json={
                "parameters": station.to_dict(),
                "raster": "default",
                "valid_from": "2000-01-01T00:00:00Z",
            },
        )
        assert calibration.status_code == 201, calibration.text


def _upload(live: LiveServer, pixels: np.ndarray) -> str:
    with live.client("station") as cam:
        response = cam.post(
            "/acquisitions",
            files=[("files", ("back.npy", npy_bytes(pixels)))],
            data={
                "patient": PATIENT_ID,
                "station": "clinic-1",
                "acquired_at": ACQUIRED,
                "operator": "nurse A",
            },
        )
        assert response.status_code == 201, response.text
        return response.json()["uid"]


def _process(client: httpx.Client, uids: list[str]) -> None:
    run_job(client, uids, until="analysis")


def test_analysis_for_clinicians_and_researchers(live: LiveServer, back_frame) -> None:
    _calibrate(live)
    uid = _upload(live, back_frame)
    with live.client("clinician") as c:
        missing = c.get(f"/acquisitions/{uid}/analysis")
        assert missing.status_code == 404 and "process it first" in missing.json()["detail"]
        assert c.get(f"/acquisitions/{uid}/analysis/report.png").status_code == 404
        assert c.get(f"/acquisitions/{'f' * 32}/analysis").status_code == 404
        _process(c, [uid])
        got = c.get(f"/acquisitions/{uid}/analysis")
        assert got.status_code == 200, got.text
        document = got.json()
        assert (
            c.get(
                f"/acquisitions/{uid}/analysis", headers={"If-None-Match": got.headers["etag"]}
            ).status_code
            == 304
        )
        report = c.get(f"/acquisitions/{uid}/analysis/report.png")
        assert report.status_code == 200 and report.headers["content-type"] == "image/png"
        page = cv2.imdecode(np.frombuffer(report.content, np.uint8), cv2.IMREAD_COLOR)
        assert page is not None and page.shape[1] > page.shape[0] > 800
        pdf = c.get(f"/acquisitions/{uid}/analysis/report.pdf")
        assert pdf.status_code == 200 and pdf.content.startswith(b"%PDF")
        assert pdf.headers["content-type"] == "application/pdf"
    assert document["uid"] == uid and document["format"] == "rasterserver.back-shape/1"
    assert document["acquisition"] == {
        "uid": uid,
        "patient": PATIENT_ID,
        "acquired_at": "2025-03-01T09:15:00Z",
    }
    assert document["frame"]["unit"] == "mm" and document["frame"]["gravity"] == [0, 1, 0]
    assert document["frame"]["calibration"] == "clinic-1:1"
    assert list(document["landmarks"]) == list(LANDMARKS)
    assert document["landmarks"]["VP"] is not None and len(document["landmarks"]["VP"]) == 3
    assert all(set(p) == {"value", "unit", "spread"} for p in document["parameters"].values())
    (frame,) = document["frames"]
    assert frame["index"] == 0 and frame["analysed"]
    assert frame["provenance"]["plugin"] == "analysis.back-shape"

    with live.client("researcher") as r:
        seen = r.get(f"/acquisitions/{uid}/analysis")
        assert seen.status_code == 200, seen.text
        assert seen.headers["etag"] != got.headers["etag"]  # another view of the same data
        assert PATIENT_ID not in seen.text and PATIENT_NAME not in seen.text
        assert "nurse" not in seen.text
        pseudonymised = seen.json()
        report = r.get(f"/acquisitions/{uid}/analysis/report.png")
        assert report.status_code == 200
    with live.archive() as archive:
        pseudonyms = Pseudonymiser(archive)
        pseudonym, shift = pseudonyms.pseudonym(PATIENT_ID), pseudonyms.shift_days(PATIENT_ID)
    assert pseudonymised["acquisition"]["patient"] == pseudonym
    shifted = dt.datetime.fromisoformat(pseudonymised["acquisition"]["acquired_at"])
    assert shifted - TRUE_TIME == dt.timedelta(days=shift)
    # the provenance's time is shifted with the same offset; the measurements are the same
    true_made = dt.datetime.fromisoformat(frame["provenance"]["created_at"])
    made = dt.datetime.fromisoformat(pseudonymised["frames"][0]["provenance"]["created_at"])
    assert made - true_made == dt.timedelta(days=shift)
    for key in ("landmarks", "parameters", "reasons", "frame"):
        assert pseudonymised[key] == document[key]

    with live.client("station") as cam:
        assert cam.get(f"/acquisitions/{uid}/analysis").status_code == 403
    with live.client("admin") as admin:
        assert admin.get(f"/acquisitions/{uid}/analysis/report.png").status_code == 403
    with live.archive() as archive:
        reads = [
            (e.actor, e.route, e.status)
            for e, who in audit_events(archive, patient=PATIENT_ID, limit=1000)
            if "analysis" in e.route
        ]
    assert ("clinician-1", "/acquisitions/{uid}/analysis", 404) in reads
    assert ("clinician-1", "/acquisitions/{uid}/analysis", 200) in reads
    assert ("researcher-1", "/acquisitions/{uid}/analysis", 200) in reads
    assert ("researcher-1", "/acquisitions/{uid}/analysis/report.png", 200) in reads
    assert ("clinician-1", "/acquisitions/{uid}/analysis/report.pdf", 200) in reads


def test_an_empty_analysis_answers_422_with_its_reason(live_sqlite: LiveServer, back_frame) -> None:
    live = live_sqlite
    _calibrate(live)
    uid = _upload(live, np.zeros_like(back_frame))  # no raster lines: nothing to analyse
    with live.client("clinician") as c:
        _process(c, [uid])
        for path in ("analysis", "analysis/report.png", "analysis/report.pdf"):
            refused = c.get(f"/acquisitions/{uid}/{path}")
            assert refused.status_code == 422, refused.text
            body = refused.json()
            assert body["error"] == "AnalysisRefusedError" and body["status"] == 422
            assert body["detail"].startswith(f"no back-shape analysis of acquisition {uid}: ")
