"""The core flow against a real uvicorn server, on SQLite and PostgreSQL: upload, read,
ETags, pseudonyms, audit rows, limits and JSON errors."""

from __future__ import annotations

import datetime as dt
import http.client
import logging
import time
from pathlib import Path

import numpy as np
import pytest
from api_helpers import PATIENT_ID, PATIENT_NAME, LiveServer, frame, npy_bytes
from sqlalchemy import select, text

from rasterserver.api.app import ApiSettings
from rasterserver.catalog.auth_models import AuditEvent
from rasterserver.config import Settings, sqlite_url
from rasterserver.services.audit_trail import audit_events
from rasterserver.services.pseudonyms import Pseudonymiser


def _upload(live: LiveServer, role: str = "clinician", **data: str):
    frames = [("files", ("a.npy", npy_bytes(frame(1)))),
              ("files", ("b.npy", npy_bytes(frame(2, np.uint16))))]
    fields = {"patient": PATIENT_ID, "roles": "raster", "station": "clinic-1",
              "acquired_at": "2025-03-01T10:00:00Z", "operator": "nurse A"} | data
    with live.client(role) as c:
        return c.post("/acquisitions", files=frames, data=fields)


def test_upload_read_frames_and_etags(live: LiveServer) -> None:
    with live.client() as anon:
        assert anon.get("/health").json()["status"] == "ok"
        assert anon.get("/patients").status_code == 401
    response = _upload(live, role="station")
    assert response.status_code == 201, response.text
    acq = response.json()
    assert acq["patient"] == PATIENT_ID and len(acq["frames"]) == 2
    uid = acq["uid"]
    with live.client("clinician") as c:
        listed = c.get("/acquisitions", params={"patient": PATIENT_ID, "limit": 10}).json()
        assert [a["uid"] for a in listed] == [uid]
        assert c.get("/acquisitions", params={"since": "2025-03-02T00:00:00Z"}).json() == []
        assert c.get(f"/acquisitions/{uid}").json()["frames"][1]["dtype"] == "uint16"
        raw = c.get(f"/acquisitions/{uid}/frames/1")
        assert raw.status_code == 200
        np.testing.assert_array_equal(np.load(__import__("io").BytesIO(raw.content)),
                                      frame(2, np.uint16))
        etag = raw.headers["etag"]
        assert etag.strip('"') == acq["frames"][1]["sha256"]
        assert c.get(f"/acquisitions/{uid}/frames/1",
                     headers={"If-None-Match": etag}).status_code == 304
        png = c.get(f"/acquisitions/{uid}/frames/0/preview.png")
        assert png.headers["content-type"] == "image/png" and png.content[:4] == b"\x89PNG"
        missing = c.get(f"/acquisitions/{uid}/frames/7")
        assert missing.status_code == 404 and missing.json()["error"] == "NotFoundError"
        visits = c.get(f"/patients/{PATIENT_ID}/visits").json()
        assert visits == [{"visit_date": "2025-03-01", "notes": ""}]


def test_a_refused_frame_stores_nothing(live: LiveServer) -> None:
    frames = [("files", ("good.npy", npy_bytes(frame(1)))),
              ("files", ("bad.png", b"\x89PNG not really"))]
    with live.client("clinician") as c:
        response = c.post("/acquisitions", files=frames, data={"patient": PATIENT_ID})
        assert response.status_code == 422
        assert response.json()["error"] == "InputError"
        assert c.get("/acquisitions").json() == []
        unknown = c.post("/acquisitions", files=frames[:1], data={"patient": "nobody"})
        assert unknown.status_code == 404
    with live.archive() as archive:
        assert archive.verify().ok and archive.acquisitions() == []


def test_researcher_sees_pseudonyms_and_shifted_dates(live: LiveServer) -> None:
    first = _upload(live, acquired_at="2025-03-01T10:00:00Z").json()
    second = _upload(live, acquired_at="2025-09-15T08:30:00Z").json()
    with live.client("researcher") as r:
        (patient,) = r.get("/patients").json()
        assert patient["pseudonymised"] and patient["name"] is None
        assert patient["birth_date"] is None and PATIENT_ID not in str(patient)
        pseudonym = patient["id"]
        assert r.get(f"/patients/{pseudonym}").json()["id"] == pseudonym
        assert r.get(f"/patients/{PATIENT_ID}").status_code == 404
        rows = r.get("/acquisitions", params={"patient": pseudonym}).json()
        assert {a["patient"] for a in rows} == {pseudonym}
        assert all(a["operator"] is None and a["notes"] is None for a in rows)
        when = {a["uid"]: dt.datetime.fromisoformat(a["acquired_at"]) for a in rows}
        true = {first["uid"]: dt.datetime(2025, 3, 1, 10, tzinfo=dt.UTC),
                second["uid"]: dt.datetime(2025, 9, 15, 8, 30, tzinfo=dt.UTC)}
        # the interval between visits survives, the calendar dates do not
        assert when[second["uid"]] - when[first["uid"]] == true[second["uid"]] - true[first["uid"]]
        with live.archive() as archive:
            shift = Pseudonymiser(archive).shift_days(PATIENT_ID)
        assert when[first["uid"]] - true[first["uid"]] == dt.timedelta(days=shift)
        visits = r.get(f"/patients/{pseudonym}/visits").json()
        assert len(visits) == 2 and all(v["notes"] is None for v in visits)
        assert r.get("/acquisitions", params={"since": "2025-01-01"}).status_code == 422
        assert r.post("/acquisitions", files=[("files", ("a.npy", npy_bytes(frame())))],
                      data={"patient": PATIENT_ID}).status_code == 403


def test_audit_rows_for_reads_writes_and_refusals(live: LiveServer) -> None:
    uid = _upload(live).json()["uid"]
    with live.client("clinician") as c:
        c.get(f"/acquisitions/{uid}/frames/0")
    with live.client("researcher") as r:
        r.get("/audit")  # refused, and audited as such
    with live.archive() as archive:
        events = audit_events(archive, patient=PATIENT_ID)
        assert [(e.actor, e.action, e.route, e.status) for e, _ in events] == [
            ("clinician-1", "C", "/acquisitions", 201),
            ("clinician-1", "R", "/acquisitions/{uid}/frames/{index}", 200),
        ]
        assert all(who == [PATIENT_ID] and e.acquisition_uid == uid for e, who in events)
        refused = audit_events(archive, actor="researcher-1")
        assert [(e.route, e.status) for e, _ in refused] == [("/audit", 403)]
        # append-only in the database itself
        with pytest.raises(Exception, match="append-only"), archive.engine.begin() as conn:
            conn.execute(text("UPDATE audit_event SET actor = 'someone else'"))
        with pytest.raises(Exception, match="append-only"), archive.engine.begin() as conn:
            conn.execute(text("DELETE FROM audit_event"))
        with archive.session() as s:
            assert s.scalar(select(AuditEvent).where(AuditEvent.actor == "someone else")) is None
    with live.client("admin") as a:
        bundle = a.get("/audit", params={"format": "fhir", "patient": PATIENT_ID}).json()
        assert bundle["resourceType"] == "Bundle" and bundle["total"] == 2
        event = bundle["entry"][1]["resource"]
        assert event["resourceType"] == "AuditEvent" and event["action"] == "R"
        assert event["outcome"] == "0" and event["agent"][0]["who"]["display"] == "clinician-1"
        assert {"value": PATIENT_ID} in [e["what"].get("identifier") for e in event["entity"]]
        assert a.get("/audit").json()[0]["actor"] == "clinician-1"
        # admins manage the archive but see no patient data
        assert a.get("/patients").status_code == 403


def test_tokens_revoked_or_invalid_are_refused(live: LiveServer) -> None:
    from rasterserver.services import auth

    with live.client("clinician") as c:
        assert c.get("/patients").status_code == 200
    with live.archive() as archive:
        (info,) = auth.tokens(archive, account="clinician-1")
        auth.revoke_token(archive, info.id)
        assert auth.authenticate(archive, live.tokens["clinician"]) is None
    with live.client("clinician") as c:
        assert c.get("/patients").status_code == 401
    with live.client(token="rs_forged") as c:
        refused = c.get("/patients")
        assert refused.status_code == 401 and refused.json()["error"] == "Unauthorized"


def test_limits_and_json_errors(live: LiveServer) -> None:
    big = [("files", ("big.npy", b"\0" * (9 * 1024 * 1024)))]
    with live.client("clinician") as c:
        too_big = c.post("/acquisitions", files=big, data={"patient": PATIENT_ID})
        assert too_big.status_code == 413 and too_big.json()["error"] == "PayloadTooLarge"
        for response in (
            c.get("/acquisitions", params={"limit": -1}),
            c.get("/acquisitions", params={"since": "yesterday"}),
            c.post("/patients", content=b"{not json", headers={"content-type": "application/json"}),
            c.post("/patients", json={"identifier": ""}),
            c.get("/no/such/route"),
            c.delete("/patients"),
        ):
            assert 400 <= response.status_code < 500, response.text
            assert response.headers["content-type"] == "application/json"
            assert "detail" in response.json()
        assert c.post("/patients", json={"identifier": PATIENT_ID}).status_code == 409
    with live.archive() as archive:
        assert archive.acquisitions() == []


def test_a_keep_alive_connection_is_closed_once_it_is_old(start_server,
                                                         tmp_path: Path) -> None:
    """So that long-lived clients spread over the worker processes (LimitsMiddleware)."""
    root = tmp_path / "archive"
    live = start_server(Settings(archive=root, database_url=sqlite_url(root)),
                        ApiSettings(keepalive_s=0.5))
    host, port = live.url.removeprefix("http://").split(":")
    auth = {"Authorization": f"Bearer {live.tokens['clinician']}"}
    for _ in range(2):  # the clock starts again on a new connection
        conn = http.client.HTTPConnection(host, int(port), timeout=10)
        try:
            sockets = set()
            for n in range(4):
                if n == 3:
                    time.sleep(0.6)
                conn.request("GET", f"/patients/{PATIENT_ID}", headers=auth)
                sockets.add(id(conn.sock))
                response = conn.getresponse()
                assert response.status == 200
                response.read()
                closes = response.getheader("connection", "").lower() == "close"
                assert closes == (n == 3), n
            assert len(sockets) == 1  # the four went over one connection
            assert conn.sock is None  # closed after the last, as announced
        finally:
            conn.close()


def test_patient_data_never_reaches_the_log(live: LiveServer, caplog) -> None:
    caplog.set_level(logging.DEBUG)
    _upload(live)
    with live.client("clinician") as c:
        c.post("/patients", json={"identifier": "MRN-99", "name": "Max Muster",
                                  "birth_date": "2010-05-04"})
        c.get(f"/patients/{PATIENT_ID}")
        c.get("/patients/MRN-99")
        c.get("/acquisitions", params={"patient": PATIENT_ID})
        c.get("/patients/MRN-unknown-77")
        c.post("/patients", json={"identifier": PATIENT_ID, "name": PATIENT_NAME})
    server_records = [r for r in caplog.records if not r.name.startswith(("httpx", "httpcore"))]
    assert any(r.name == "rasterserver.api.access" for r in server_records)
    text_logged = "\n".join(r.getMessage() for r in server_records)
    for secret in (PATIENT_ID, PATIENT_NAME, "MRN-99", "Max Muster", "2010-05-04",
                   "MRN-unknown-77", "Erika"):
        assert secret not in text_logged


def test_metrics_name_route_templates_only(live: LiveServer) -> None:
    _upload(live)
    with live.client("clinician") as c:
        c.get(f"/patients/{PATIENT_ID}")
    with live.client("admin") as a:
        text_out = a.get("/metrics").text
    assert 'route="/patients/{patient}",status="200"' in text_out
    assert "rasterserver_request_seconds_bucket" in text_out and PATIENT_ID not in text_out


def test_no_data_leaves_without_its_audit_row(live_sqlite: LiveServer, monkeypatch) -> None:
    from rasterserver.services import audit

    def broken(*_args, **_kwargs) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(audit, "insert_records", broken)
    with live_sqlite.client("clinician") as c:
        response = c.get(f"/patients/{PATIENT_ID}")
    assert response.status_code == 503 and response.json()["error"] == "AuditUnavailable"
    assert PATIENT_NAME not in response.text


def test_unexpected_errors_log_no_values(live_sqlite: LiveServer, monkeypatch, caplog) -> None:
    from rasterserver.archive import Archive

    def broken(self, identifier):
        raise RuntimeError(f"statement failed with parameters ({identifier!r})")

    monkeypatch.setattr(Archive, "patient_info", broken)
    caplog.set_level(logging.DEBUG)
    with live_sqlite.client("clinician") as c:
        response = c.get(f"/patients/{PATIENT_ID}")
    assert response.status_code == 500 and response.json()["error"] == "InternalError"
    assert PATIENT_ID not in response.text
    logged = "\n".join(r.getMessage() + (r.exc_text or "") for r in caplog.records
                       if not r.name.startswith(("httpx", "httpcore")))
    assert "RuntimeError" in logged and PATIENT_ID not in logged
    monkeypatch.undo()
    with live_sqlite.archive() as archive:  # the failed request is audited like any other
        assert [e.status for e, _ in audit_events(archive, actor="clinician-1")] == [500]


def test_patient_and_visit_filters(live: LiveServer) -> None:
    _upload(live, acquired_at="2025-03-01T10:00:00Z")
    _upload(live, acquired_at="2025-09-15T08:30:00Z")
    with live.client("clinician") as c:
        for ident, sex in (("MRN-1_x", "female"), ("MRN-1%y", "male"), ("OTHER-1", "female")):
            assert c.post("/patients", json={"identifier": ident, "sex": sex}).status_code == 201

        def ids(**params: str) -> list[str]:
            return [p["id"] for p in c.get("/patients", params=params).json()]

        assert ids(identifier_prefix="MRN-1_") == ["MRN-1_x"]  # _ and % are literal
        assert ids(identifier_prefix="MRN-1%") == ["MRN-1%y"]
        assert ids(sex="female") == ["MRN-1_x", "OTHER-1"]
        assert ids(identifier_prefix="MRN-", sex="female", limit="1", offset="0") == ["MRN-1_x"]
        visits = c.get(f"/patients/{PATIENT_ID}/visits", params={"since": "2025-06-01"}).json()
        assert [v["visit_date"] for v in visits] == ["2025-09-15"]
    with live.client("researcher") as r:
        assert r.get("/patients", params={"identifier_prefix": "MRN"}).status_code == 422
        assert len(r.get("/patients", params={"sex": "female"}).json()) == 2


def test_a_retried_upload_with_an_idempotency_key_is_stored_once(live: LiveServer) -> None:
    frames = [("files", ("a.npy", npy_bytes(frame(1))))]
    fields = {"patient": PATIENT_ID, "station": "clinic-1", "acquired_at": "2025-03-01T10:00:00Z"}
    with live.client("station") as c:
        key = {"Idempotency-Key": "cam-3/2025-03-01/0001"}
        first = c.post("/acquisitions", files=frames, data=fields, headers=key)
        again = c.post("/acquisitions", files=frames, data=fields, headers=key)
        other = c.post("/acquisitions", files=[("files", ("a.npy", npy_bytes(frame(2))))],
                       data=fields, headers=key)
        unkeyed = c.post("/acquisitions", files=frames, data=fields)
    assert first.status_code == 201 and "idempotent-replayed" not in first.headers
    assert again.status_code == 200 and again.headers["idempotent-replayed"] == "true"
    assert again.json() == first.json()
    assert other.status_code == 409 and other.json()["error"] == "ConflictError"
    assert unkeyed.status_code == 201 and unkeyed.json()["uid"] != first.json()["uid"]
    with live.archive() as archive:
        assert len(archive.find(patient=PATIENT_ID)) == 2  # the keyed one once, the unkeyed
        assert archive.verify().ok
