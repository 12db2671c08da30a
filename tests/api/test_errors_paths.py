"""A damaged archive file over HTTP, on a live server (SQLite and PostgreSQL): the 500 says
that stored data is damaged without showing where the archive lives or how it is laid out;
the server log names the file. Errors of runs and jobs kept for clients do not show the
archive's folder either."""

from __future__ import annotations

import logging
import time

from api_helpers import PATIENT_ID, LiveServer, frame, npy_bytes

from rasterserver.api.errors import scrub_paths


def _damage(live: LiveServer, uid: str) -> str:
    with live.archive() as archive:
        path = archive.raw.path_for(uid)
    path.chmod(0o600)
    data = bytearray(path.read_bytes())
    data[:8] = b"NOT HDF5"  # the signature: h5py cannot open it any more
    path.write_bytes(bytes(data))
    return str(path)


def test_a_500_on_a_damaged_file_keeps_the_path_in_the_log(live: LiveServer, caplog) -> None:
    with live.client("clinician") as c:
        uid = c.post("/acquisitions", files=[("files", ("a.npy", npy_bytes(frame())))],
                     data={"patient": PATIENT_ID}).json()["uid"]
        where = _damage(live, uid)
        root = str(live.settings.archive)
        with caplog.at_level(logging.ERROR, logger="rasterserver.api.errors"):
            got = c.get(f"/acquisitions/{uid}/frames/0")
        assert got.status_code == 500, got.text
        body = got.json()
        assert body["error"] == "IntegrityError" and "damaged" in body["detail"]
        for secret in (root, where, "raw/", ".h5", uid[:2] + "/" + uid[2:4]):
            assert secret not in got.text, secret
        logged = "\n".join(r.getMessage() for r in caplog.records)
        assert f"{uid}.h5" in logged and "unreadable HDF5 file" in logged
        assert PATIENT_ID not in logged

        # processing the damaged acquisition fails; its run's and job's errors are shown
        # without the archive's folder
        job = c.post("/jobs", json={"uids": [uid]}).json()
        state = c.get(f"/jobs/{job['id']}").json()
        for _ in range(600):
            if state["status"] not in ("queued", "running"):
                break
            time.sleep(0.2)
            state = c.get(f"/jobs/{job['id']}").json()
        assert state["status"] == "failed", state
        runs = c.get(f"/acquisitions/{uid}/runs")
        assert runs.status_code == 200
        assert root not in runs.text and root not in str(state)


def test_scrub_paths() -> None:
    assert scrub_paths("/srv/a/raw/x.h5: bad", "/srv/a") == "<archive>/raw/x.h5: bad"
    assert scrub_paths("nothing here", "/srv/a") == "nothing here"
    assert scrub_paths("a.b", ".") == "a.b" and scrub_paths("x", "") == "x"
