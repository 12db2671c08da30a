"""Processing on demand and exports over HTTP, on a live server: calibration by the admin,
upload by a station, a job polled to the end, results with ETags, meshes and points."""

from __future__ import annotations

import io
import time

import geometry_truth as gt
import numpy as np
import open3d as o3d
from api_helpers import PATIENT_ID, LiveServer, npy_bytes


def test_process_job_results_and_exports(live_sqlite: LiveServer, tmp_path) -> None:
    live = live_sqlite
    station = gt.station()
    with live.client("admin") as admin:
        assert admin.post("/rasters", json={"name": "default", "definition":
                                            station.raster_definition.to_dict()}).status_code == 201
        cal = admin.post("/stations/clinic-1/calibrations",
                         json={"parameters": station.to_dict(), "raster": "default"})
        assert cal.status_code == 201 and cal.json()["version"] == 1
        got = admin.get("/stations/clinic-1/calibrations/1")
        assert admin.get("/stations/clinic-1/calibrations/1", headers={
            "If-None-Match": got.headers["etag"]}).status_code == 304
    image = gt.rendering("back").image
    with live.client("station") as cam:
        uid = cam.post("/acquisitions", files=[("files", ("back.npy", npy_bytes(image)))],
                       data={"patient": PATIENT_ID, "station": "clinic-1"}).json()["uid"]
    with live.client("clinician") as c:
        assert c.get(f"/acquisitions/{uid}/export").status_code == 404  # not processed yet
        job = c.post("/jobs", json={"uids": [uid]})
        assert job.status_code == 202, job.text
        job_id = job.json()["id"]
        deadline = time.monotonic() + 300
        while (state := c.get(f"/jobs/{job_id}").json())["status"] in ("queued", "running"):
            assert time.monotonic() < deadline
            time.sleep(0.5)
        assert state["status"] == "done", state
        assert state["done"] == state["total"] == 1
        # by default a job computes the mesh and the back-shape analysis, as `process` does
        assert state["outcomes"][0]["computed"] == 8
        assert c.get("/jobs", params={"status": "done"}).json()[0]["id"] == job_id
        results = c.get(f"/acquisitions/{uid}/results").json()
        assert [r["stage"] for r in results] == ["peaks", "lines", "order", "numbers", "points",
                                                 "surface", "mesh", "analysis"]
        mesh_row = c.get(f"/acquisitions/{uid}/results/mesh")
        assert mesh_row.headers["etag"].strip('"') == results[-2]["output_checksum"]
        assert c.get(f"/acquisitions/{uid}/results/mesh",
                     headers={"If-None-Match": mesh_row.headers["etag"]}).status_code == 304
        assert c.get(f"/acquisitions/{uid}/runs").json()[0]["status"] == "done"
        for fmt in ("ply", "obj", "stl"):
            exported = c.get(f"/acquisitions/{uid}/export", params={"format": fmt})
            assert exported.status_code == 200, exported.text
            path = tmp_path / f"back.{fmt}"
            path.write_bytes(exported.content)
            assert len(o3d.io.read_triangle_mesh(str(path)).triangles) > 30_000
        body = c.get(f"/acquisitions/{uid}/export", params={"format": "ply",
                                                            "frame": "patient"})
        assert body.status_code == 200 and body.headers["x-coordinate-frame"].startswith(
            "patient")
        assert body.content != c.get(f"/acquisitions/{uid}/export",
                                     params={"format": "ply"}).content
        csv = c.get(f"/acquisitions/{uid}/export", params={"format": "csv"})
        header, *rows = csv.text.splitlines()
        assert header.startswith("x_mm,y_mm,z_mm") and len(rows) > 15_000
        refused = c.get(f"/acquisitions/{uid}/export", params={"format": "stl",
                                                               "what": "points"})
        assert refused.status_code == 422
        # a second job reuses every stored result
        again = c.post("/jobs", json={"uids": [uid]}).json()["id"]
        while (state := c.get(f"/jobs/{again}").json())["status"] in ("queued", "running"):
            time.sleep(0.2)
        assert state["outcomes"][0]["reused"] == 8
        assert c.post("/jobs", json={"uids": ["f" * 32]}).status_code == 404
    with live.client("researcher") as r:
        points = r.get(f"/acquisitions/{uid}/export", params={"format": "ply",
                                                              "what": "points"})
        cloud = o3d.t.io.read_point_cloud  # the researcher gets the same data, pseudonymised
        path = tmp_path / "points.ply"
        path.write_bytes(points.content)
        assert cloud(str(path)).point.positions.shape[0] > 15_000
        frame0 = np.load(io.BytesIO(r.get(f"/acquisitions/{uid}/frames/0").content))
        np.testing.assert_array_equal(frame0, image)
        assert r.post("/jobs", json={"uids": [uid]}).status_code == 403
