"""The comparison of two acquisitions and a patient's trends over HTTP, on a live server
(SQLite and PostgreSQL): JSON and PNG for clinicians, pseudonym and shifted dates (true
intervals) for researchers, 422 for other patients' acquisitions, 404 before processing,
403 for stations, and the audit trail of every read."""

from __future__ import annotations

import csv
import datetime as dt
import io

import cv2
import httpx
import numpy as np
import pytest
from api_helpers import PATIENT_ID, PATIENT_NAME, LiveServer, npy_bytes, run_job
from backshape_truth import simulated
from test_api_analysis import _calibrate

from rasterserver.services.audit_trail import audit_events
from rasterserver.services.pseudonyms import Pseudonymiser

FIRST, SECOND = "2024-03-01T10:15:00+01:00", "2025-03-11T10:15:00+01:00"
INTERVAL = dt.timedelta(days=375)


@pytest.fixture(scope="module")
def two_backs() -> tuple[np.ndarray, np.ndarray]:
    """One simulated back rendered twice with independent noise (seconds: once)."""
    return simulated("moderate", seed=1)[0], simulated("moderate", seed=2)[0]


def _process(client: httpx.Client, uids: list[str]) -> None:
    """The default job: the mesh and the analysis, as `rasterserver process`."""
    run_job(client, uids)


def _upload(live: LiveServer, pixels: np.ndarray, when: str, patient: str = PATIENT_ID) -> str:
    with live.client("station") as cam:
        response = cam.post(
            "/acquisitions",
            files=[("files", ("back.npy", npy_bytes(pixels)))],
            data={"patient": patient, "station": "clinic-1", "acquired_at": when},
        )
        assert response.status_code == 201, response.text
        return response.json()["uid"]


def test_comparison_and_trends(live: LiveServer, two_backs) -> None:
    _calibrate(live)
    first, second = (_upload(live, b, w) for b, w in zip(two_backs, (FIRST, SECOND), strict=True))
    with live.client("clinician") as c:
        assert c.post("/patients", json={"identifier": "MRN-0000002"}).status_code == 201
    other = _upload(live, two_backs[0], SECOND, patient="MRN-0000002")
    path = f"/acquisitions/{first}/comparison/{second}"
    with live.client("clinician") as c:
        missing = c.get(path)
        assert missing.status_code == 404 and "process it first" in missing.json()["detail"]
        assert c.get(f"{path}/distance.png").status_code == 404
        assert c.get(f"/patients/{PATIENT_ID}/trends").status_code == 404
        _process(c, [first, second])
        got = c.get(path)
        assert got.status_code == 200, got.text
        document = got.json()
        # either order: the earlier visit is A
        reverse = c.get(f"/acquisitions/{second}/comparison/{first}").json()
        assert (reverse["a"], reverse["b"]) == (first, second)
        picture = c.get(f"{path}/distance.png")
        assert picture.status_code == 200 and picture.headers["content-type"] == "image/png"
        image = cv2.imdecode(np.frombuffer(picture.content, np.uint8), cv2.IMREAD_COLOR)
        assert image is not None and image.shape[0] > 300
        refused = c.get(f"/acquisitions/{first}/comparison/{other}")
        assert refused.status_code == 422 and "different patients" in refused.json()["detail"]
        assert c.get(f"/acquisitions/{first}/comparison/{first}").status_code == 422
        assert c.get(f"/acquisitions/{first}/comparison/{'f' * 32}").status_code == 404
        trends = c.get(f"/patients/{PATIENT_ID}/trends")
        assert trends.status_code == 200, trends.text
        table = c.get(f"/patients/{PATIENT_ID}/trends", params={"format": "csv"})
        assert table.status_code == 200 and table.headers["content-type"].startswith("text/csv")
        assert c.get("/patients/MRN-9999999/trends").status_code == 404
    assert (document["a"], document["b"]) == (first, second)
    assert [a["patient"] for a in document["acquisitions"]] == [PATIENT_ID, PATIENT_ID]
    assert document["registration"]["fitness"] > 0.5
    assert document["registration"]["rmse_mm"] < 2.0
    assert len(document["registration"]["transform"]) == 4
    assert document["distance"]["rms_mm"] < 2.0  # the same back, rendered twice
    assert set(document["asymmetry"]) == {first, second}
    assert "files" not in document and ".png" not in got.text and ".ply" not in got.text
    when = [dt.datetime.fromisoformat(a["acquired_at"]) for a in document["acquisitions"]]
    assert when[1] - when[0] == INTERVAL

    trend = trends.json()
    assert trend["patient"] == PATIENT_ID and trend["format"] == "rasterserver.trends/1"
    rows = {r["parameter"]: r for r in trend["parameters"]}
    assert "scoliosis_angle_deg" in rows
    row = rows["scoliosis_angle_deg"]
    assert [v["label"] for v in row["visits"]] == [first, second]
    assert row["visits"][0]["date"] == "2024-03-01T09:15:00+00:00"
    assert {"flagged", "change", "value", "vp_carried_from"} <= set(row["visits"][1])
    assert row["visits"][1]["vp_carried_from"] is None  # both visits found their own VP
    lines = list(csv.DictReader(io.StringIO(table.text)))
    assert len(lines) == 2 * len(rows) and lines[0]["visit"] == first

    with live.client("researcher") as r:
        seen = r.get(path)
        assert seen.status_code == 200, seen.text
        assert PATIENT_ID not in seen.text and PATIENT_NAME not in seen.text
        assert r.get(f"{path}/distance.png").status_code == 200
        with live.archive() as archive:
            pseudonyms = Pseudonymiser(archive)
            pseudonym, shift = pseudonyms.pseudonym(PATIENT_ID), pseudonyms.shift_days(PATIENT_ID)
        shown = r.get(f"/patients/{pseudonym}/trends")
        assert shown.status_code == 200, shown.text
        assert PATIENT_ID not in shown.text
        shown_csv = r.get(f"/patients/{pseudonym}/trends?format=csv")
        assert shown_csv.status_code == 200 and PATIENT_ID not in shown_csv.text
    hidden = seen.json()
    assert [a["patient"] for a in hidden["acquisitions"]] == [pseudonym, pseudonym]
    shifted = [dt.datetime.fromisoformat(a["acquired_at"]) for a in hidden["acquisitions"]]
    assert [s - w for s, w in zip(shifted, when, strict=True)] == [dt.timedelta(days=shift)] * 2
    assert shifted[1] - shifted[0] == INTERVAL
    # the same measurements (ICP's last digits vary from run to run)
    for key in ("fitness", "rmse_mm"):
        assert hidden["registration"][key] == pytest.approx(document["registration"][key])
    assert hidden["distance"]["rms_mm"] == pytest.approx(document["distance"]["rms_mm"])
    trend_r = shown.json()
    assert trend_r["patient"] == pseudonym
    dates = [
        dt.datetime.fromisoformat(v["date"])
        for v in {r["parameter"]: r for r in trend_r["parameters"]}["scoliosis_angle_deg"]["visits"]
    ]
    assert dates[0] - dt.datetime(2024, 3, 1, 9, 15, tzinfo=dt.UTC) == dt.timedelta(days=shift)
    assert dates[1] - dates[0] == INTERVAL
    values = [[v["value"] for v in p["visits"]] for p in trend["parameters"]]
    assert [[v["value"] for v in p["visits"]] for p in trend_r["parameters"]] == values

    with live.client("station") as cam:
        assert cam.get(path).status_code == 403
        assert cam.get(f"{path}/distance.png").status_code == 403
        assert cam.get(f"/patients/{PATIENT_ID}/trends").status_code == 403
    with live.client("admin") as admin:
        assert admin.get(f"/patients/{PATIENT_ID}/trends").status_code == 403
    with live.archive() as archive:
        reads = [
            (e.actor, e.route, e.status)
            for e, _who in audit_events(archive, patient=PATIENT_ID, limit=1000)
            if "comparison" in e.route or "trends" in e.route
        ]
    template = "/acquisitions/{uid_a}/comparison/{uid_b}"
    assert ("clinician-1", template, 404) in reads
    assert ("clinician-1", template, 200) in reads
    assert ("researcher-1", template, 200) in reads
    assert ("researcher-1", template + "/distance.png", 200) in reads
    assert ("clinician-1", "/patients/{patient}/trends", 200) in reads
    assert ("researcher-1", "/patients/{patient}/trends", 200) in reads
