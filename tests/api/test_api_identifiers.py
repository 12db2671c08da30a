"""Patient identifiers over HTTP: the rules, look-alikes, and every stored one reachable."""

from __future__ import annotations

from urllib.parse import quote

from api_helpers import LiveServer, frame, npy_bytes
from sqlalchemy import text


def _path(identifier: str) -> str:
    return "/patients/" + quote(identifier, safe="")


def test_identifiers_that_break_the_rules_are_refused(live: LiveServer) -> None:
    with live.client("clinician") as c:
        for identifier in ("SL/01", "a\x00b", "a\nb", " P-2", "P-2 ", "P\u00a02", "..", "x" * 65):
            answer = c.post("/patients", json={"identifier": identifier})
            assert answer.status_code == 422, (identifier, answer.text)
        with live.archive() as archive:
            assert [p.identifier for p in archive.patients()] == ["MRN-0047113"]
        # anything the rules admit is reachable, percent-encoded as one path segment
        for identifier in ("MRN 12", "a?b#c%d", "Müller:3", "...", "患者-7"):
            assert c.post("/patients", json={"identifier": identifier}).status_code == 201
            got = c.get(_path(identifier))
            assert got.status_code == 200 and got.json()["id"] == identifier
            assert c.get(_path(identifier) + "/visits").json() == []


def test_look_alikes_are_one_patient(live: LiveServer) -> None:
    with live.client("clinician") as c:
        made = c.post("/patients", json={"identifier": "e\u0301-P1"})
        assert made.status_code == 201 and made.json()["id"] == "\u00e9-P1"  # stored NFC
        for twin in ("\u00e9-P1", "\u00c9-p1", "E\u0301-\uff30\uff11"):
            assert c.post("/patients", json={"identifier": twin}).status_code == 409, twin
            assert c.get(_path(twin)).json()["id"] == "\u00e9-P1"
        upload = c.post(
            "/acquisitions",
            files=[("files", ("a.npy", npy_bytes(frame(5))))],
            data={"patient": "\u00c9-p1"},
        )
        assert upload.status_code == 201 and upload.json()["patient"] == "\u00e9-P1"
        listed = c.get("/acquisitions", params={"patient": "e\u0301-p1"}).json()
        assert [a["uid"] for a in listed] == [upload.json()["uid"]]
        found = c.get("/patients", params={"identifier_prefix": "\u00c9-"}).json()
        assert [p["id"] for p in found] == ["\u00e9-P1"]


def test_identifiers_stored_before_the_rules_stay_reachable(live: LiveServer) -> None:
    # as an archive of an earlier version could hold them (the checks were not there)
    with live.archive() as archive, archive.engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO patient (identifier, identifier_key, name, sex, "
                "created_at) VALUES ('SL/01', 'sl/01', '', 'unknown', '2026-01-01')"
            )
        )
    with live.client("clinician") as c:
        got = c.get(_path("SL/01"))
        assert got.status_code == 200 and got.json()["id"] == "SL/01"
        assert c.get(_path("SL/01") + "/visits").status_code == 200
        upload = c.post(
            "/acquisitions",
            files=[("files", ("a.npy", npy_bytes(frame(6))))],
            data={"patient": "SL/01"},
        )
        assert upload.status_code == 201
        listed = c.get("/acquisitions", params={"patient": "SL/01"}).json()
        assert [a["uid"] for a in listed] == [upload.json()["uid"]]
        assert [v["visit_date"] for v in c.get(_path("SL/01") + "/visits").json()] != []
    with live.client("researcher") as r:
        pseudonym = r.get("/acquisitions").json()[0]["patient"]
        assert r.get(_path(pseudonym)).json()["id"] == pseudonym
