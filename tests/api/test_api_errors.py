"""Refusals a client can rely on: Allow lists every method of a path; documented 4xx codes."""

from __future__ import annotations

from api_helpers import PATIENT_ID, LiveServer, frame, npy_bytes


def test_options_and_405_name_every_method_of_the_path(live_sqlite: LiveServer) -> None:
    expected = {
        "/patients": "GET, OPTIONS, POST",
        "/acquisitions": "GET, OPTIONS, POST",
        "/stations/clinic-1/calibrations": "GET, OPTIONS, POST",
        "/jobs": "GET, OPTIONS, POST",
        "/health": "GET, OPTIONS",
        f"/patients/{PATIENT_ID}": "GET, OPTIONS",
    }
    with live_sqlite.client() as anon:
        for path, allow in expected.items():
            options = anon.options(path)
            assert options.status_code == 204, (path, options.text)
            assert options.headers["allow"] == allow, path
            assert options.content == b""
        refused = anon.delete("/patients")
        assert refused.status_code == 405 and refused.headers["allow"] == "GET, OPTIONS, POST"
        assert refused.json()["error"] == "MethodNotAllowed"
        assert anon.options("/no/such/route").status_code == 404


def test_an_export_the_format_cannot_hold_is_a_documented_422(live_sqlite: LiveServer) -> None:
    with live_sqlite.client() as anon:
        document = anon.get("/openapi.json").json()
    responses = document["paths"]["/acquisitions/{uid}/export"]["get"]["responses"]
    assert "csv holds points" in responses["422"]["description"]
    assert "process it first" in responses["404"]["description"]
    with live_sqlite.client("clinician") as c:
        uid = c.post(
            "/acquisitions",
            files=[("files", ("a.npy", npy_bytes(frame(3))))],
            data={"patient": PATIENT_ID},
        ).json()["uid"]
        for params in ({"what": "mesh", "format": "csv"}, {"what": "points", "format": "stl"}):
            refused = c.get(f"/acquisitions/{uid}/export", params=params)
            assert refused.status_code == 422, refused.text
            assert refused.json()["error"] == "InputError"
        # a combination it can hold, of an acquisition not processed yet
        assert c.get(f"/acquisitions/{uid}/export", params={"format": "csv"}).status_code == 404
