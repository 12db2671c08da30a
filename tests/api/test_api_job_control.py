"""Pausing, resuming and cancelling jobs over HTTP on a live server (SQLite, PostgreSQL): the
same catalogue jobs as `rasterserver jobs pause|resume|cancel`."""

from __future__ import annotations

import time

import geometry_truth as gt
import numpy as np
from api_helpers import PATIENT_ID, LiveServer, npy_bytes

from rasterserver.processing_jobs import Selection, create_job


def _acquisitions(live: LiveServer, count: int) -> list[str]:
    station = gt.station()
    with live.client("admin") as admin:
        admin.post("/rasters", json={"name": "default",
                                     "definition": station.raster_definition.to_dict()})
        admin.post("/stations/clinic-1/calibrations",
                   json={"parameters": station.to_dict(), "raster": "default"})
    image = gt.rendering("back").image
    uids = []
    with live.client("station") as cam:
        for k in range(count):
            pixels = image if k == 0 else np.zeros_like(image) + k  # uniform frames: fast
            uids.append(cam.post("/acquisitions",
                                 files=[("files", (f"f{k}.npy", npy_bytes(pixels)))],
                                 data={"patient": PATIENT_ID, "station": "clinic-1"},
                                 ).json()["uid"])
    return uids


def test_pause_resume_cancel_over_http(live: LiveServer) -> None:
    uids = _acquisitions(live, 4)
    with live.archive() as archive:
        # queued by another process (this test): paused over HTTP before anything runs
        job, count = create_job(archive, Selection(uids=tuple(uids)), targets=["mesh"])
        other, _ = create_job(archive, Selection(uids=tuple(uids)), targets=["surface"])
    assert count == 4
    with live.client("clinician") as c:
        paused = c.post(f"/jobs/{job.id}/pause")
        assert paused.status_code == 200, paused.text
        assert paused.json()["status"] == "paused" and paused.json()["left"] == 4
        assert c.post(f"/jobs/{job.id}/pause").status_code == 409  # not queued or running

        resumed = c.post(f"/jobs/{job.id[:10]}/resume")
        assert resumed.status_code == 202, resumed.text
        assert resumed.json()["status"] in ("running", "done")
        deadline = time.monotonic() + 300
        while (state := c.get(f"/jobs/{job.id}").json())["status"] in ("queued", "running"):
            assert time.monotonic() < deadline
            time.sleep(0.2)
        assert state["status"] == "done" and state["done"] == 4, state
        assert c.post(f"/jobs/{job.id}/resume").status_code == 409  # finished
        assert c.post(f"/jobs/{job.id}/cancel").status_code == 409

        cancelled = c.post(f"/jobs/{other.id}/cancel")
        assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
        assert c.post(f"/jobs/{other.id}/resume").status_code == 409
        assert c.post(f"/jobs/{'f' * 32}/pause").status_code == 404
    with live.client("researcher") as r:
        assert r.post(f"/jobs/{job.id}/cancel").status_code == 403
