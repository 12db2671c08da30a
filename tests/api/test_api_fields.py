"""Times, dates and enumerations over HTTP, against a real server on SQLite and PostgreSQL."""

from __future__ import annotations

import datetime as dt
from typing import get_args

from api_helpers import PATIENT_ID, LiveServer, frame, npy_bytes

from rasterserver.api import fields
from rasterserver.catalog.auth_models import ACCOUNT_KINDS, ROLES
from rasterserver.catalog.models import ACQUISITION_KINDS, FRAME_ROLES, SEXES


def _upload(live: LiveServer, acquired_at: str):
    with live.client("clinician") as c:
        return c.post(
            "/acquisitions",
            files=[("files", ("a.npy", npy_bytes(frame(4))))],
            data={"patient": PATIENT_ID, "acquired_at": acquired_at},
        )


def test_an_offset_uploaded_is_the_instant_stored_and_filtered(live: LiveServer) -> None:
    response = _upload(live, "2025-03-01T10:15+05:00")
    assert response.status_code == 201, response.text
    uid = response.json()["uid"]
    assert response.json()["acquired_at"] == "2025-03-01T05:15:00Z"
    with live.archive() as archive:
        assert archive.info(uid).acquired_at == dt.datetime(2025, 3, 1, 5, 15, tzinfo=dt.UTC)
    with live.client("clinician") as c:
        assert c.get(f"/acquisitions/{uid}").json()["acquired_at"] == "2025-03-01T05:15:00Z"

        def listed(**params: str) -> list[str]:
            answer = c.get("/acquisitions", params=params)
            assert answer.status_code == 200, answer.text
            return [a["uid"] for a in answer.json()]

        assert listed(since="2025-03-01T05:15:00Z", until="2025-03-01T00:16-05:00") == [uid]
        assert listed(until="2025-03-01T10:15+05:00") == []
        assert listed(since="2025-03-01T10:15:01+05:00") == []
        assert listed(since="2025-03-01") == [uid]  # a date alone: 00:00 UTC
        # the visit is the day at the offset given
        visits = c.get(f"/patients/{PATIENT_ID}/visits").json()
        assert [v["visit_date"] for v in visits] == ["2025-03-01"]


def test_times_without_zone_and_numbers_are_refused(live: LiveServer) -> None:
    for value in ("2025-03-01T10:15", "0", "1740822900"):
        refused = _upload(live, value)
        assert refused.status_code == 422, (value, refused.text)
        assert refused.json()["detail"][0]["loc"] == ["body", "acquired_at"]
    with live.client("clinician") as c:
        for path, params in (
            ("/acquisitions", {"until": "0.5"}),
            ("/acquisitions", {"since": "0"}),
            ("/acquisitions", {"since": "2025-03-01T10:15"}),
            (f"/patients/{PATIENT_ID}/visits", {"since": "0"}),
            (f"/patients/{PATIENT_ID}/visits", {"until": "2025-03-01T00:00Z"}),
        ):
            answer = c.get(path, params=params)
            assert answer.status_code == 422, (path, params, answer.text)
        for birth_date in (0, 0.5, "0", "1970", "02.05.2011"):
            answer = c.post("/patients", json={"identifier": "P-9", "birth_date": birth_date})
            assert answer.status_code == 422, (birth_date, answer.text)
            assert answer.json()["detail"][0]["loc"] == ["body", "birth_date"]
        ok = c.post("/patients", json={"identifier": "P-9", "birth_date": "2011-05-02"})
        assert ok.status_code == 201 and ok.json()["birth_date"] == "2011-05-02"
    with live.client("admin") as c:
        assert c.get("/audit", params={"since": "0.5"}).status_code == 422
        assert c.get("/audit", params={"since": "2025-01-01T00:00Z"}).status_code == 200
    with live.archive() as archive:
        assert archive.acquisitions() == []


def test_enumerations_are_in_the_openapi_document(live: LiveServer) -> None:
    with live.client() as c:
        document = c.get("/openapi.json").json()
    schemas = document["components"]["schemas"]

    def values(schema: dict) -> list[str]:
        for option in schema.get("anyOf", [schema]):
            if "enum" in option:
                return option["enum"]
        raise AssertionError(f"no enum in {schema}")

    assert values(schemas["AccountIn"]["properties"]["role"]) == list(ROLES)
    assert values(schemas["AccountIn"]["properties"]["kind"]) == list(ACCOUNT_KINDS)
    assert values(schemas["AccountOut"]["properties"]["role"]) == list(ROLES)
    assert values(schemas["PatientIn"]["properties"]["sex"]) == list(SEXES)
    assert values(schemas["PatientOut"]["properties"]["sex"]) == list(SEXES)
    assert values(schemas["AcquisitionOut"]["properties"]["kind"]) == list(ACQUISITION_KINDS)
    params = {
        p["name"]: p["schema"] for p in document["paths"]["/acquisitions"]["get"]["parameters"]
    }
    assert values(params["kind"]) == list(ACQUISITION_KINDS)
    since = params["since"]["anyOf"][0]
    assert since == {"type": "string", "format": "date-time"}
    # one list of values: the catalogue's check constraints
    assert get_args(fields.Sex) == SEXES and get_args(fields.Role) == ROLES
    assert get_args(fields.AccountKind) == ACCOUNT_KINDS
    assert get_args(fields.AcquisitionKind) == ACQUISITION_KINDS
    assert get_args(fields.FrameRole) == FRAME_ROLES


def test_unknown_enumeration_values_are_refused(live: LiveServer) -> None:
    with live.client("clinician") as c:
        answer = c.post("/patients", json={"identifier": "P-8", "sex": "f"})
        assert answer.status_code == 422 and answer.json()["detail"][0]["loc"] == ["body", "sex"]
    with live.client("admin") as c:
        answer = c.post("/accounts", json={"name": "bob", "role": "root"})
        assert answer.status_code == 422 and answer.json()["detail"][0]["loc"] == ["body", "role"]
        assert c.get("/accounts", params={"role": "root"}).status_code == 422
