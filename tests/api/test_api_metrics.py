"""``/metrics``: exact counts per app in one process, and summed over ``serve --workers 2``."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
from api_helpers import PATIENT_ID, LiveServer, free_port
from prometheus_client.parser import text_string_to_metric_families

from rasterserver.archive import Archive
from rasterserver.config import Settings, sqlite_url
from rasterserver.services import auth


def _samples(text_out: str) -> dict[tuple[str, frozenset], float]:
    """Every sample of an exposition: (name, labels) -> value."""
    return {(s.name, frozenset(s.labels.items())): s.value
            for family in text_string_to_metric_families(text_out) for s in family.samples}


def _requests(samples: dict, method: str, route: str, status: int) -> float:
    key = frozenset({"method": method, "route": route, "status": str(status)}.items())
    return samples.get(("rasterserver_requests_total", key), 0.0)


def _observed(samples: dict, method: str, route: str) -> float:
    key = frozenset({"method": method, "route": route}.items())
    return samples.get(("rasterserver_request_seconds_count", key), 0.0)


def test_counts_are_exact_per_app_and_name_no_patient(start_server, live: LiveServer,
                                                      tmp_path: Path) -> None:
    # a second app in the same process: its registry must not see the first one's requests
    other_root = tmp_path / "other"
    other = start_server(Settings(archive=other_root, database_url=sqlite_url(other_root)))
    with live.client("clinician") as c:
        for _ in range(5):
            assert c.get(f"/patients/{PATIENT_ID}").status_code == 200
        for _ in range(3):
            assert c.get("/patients/MRN-unknown-77").status_code == 404
    with live.client("admin") as a:
        first = a.get("/metrics")
        second = a.get("/metrics").text
    assert first.status_code == 200 and first.headers["content-type"].startswith("text/plain")
    samples = _samples(first.text)
    assert _requests(samples, "GET", "/patients/{patient}", 200) == 5
    assert _requests(samples, "GET", "/patients/{patient}", 404) == 3
    assert _observed(samples, "GET", "/patients/{patient}") == 8
    # a scrape is counted once it has been answered
    assert _requests(samples, "GET", "/metrics", 200) == 0
    assert _requests(_samples(second), "GET", "/metrics", 200) == 1
    assert ("rasterserver_jobs_running", frozenset()) in samples
    assert ("rasterserver_jobs_queued", frozenset()) in samples
    for text_out in (first.text, second):
        assert PATIENT_ID not in text_out and "MRN-unknown-77" not in text_out

    with other.client("admin") as a:
        other_samples = _samples(a.get("/metrics").text)
    assert _observed(other_samples, "GET", "/patients/{patient}") == 0
    assert _requests(other_samples, "GET", "/metrics", 200) == 0


def _collect_output(stream, lines: list[str]) -> None:
    for raw in iter(stream.readline, b""):
        lines.append(raw.decode(errors="replace"))


def test_serve_with_two_workers_reports_the_sum_of_both(tmp_path: Path) -> None:
    root = tmp_path / "archive"
    settings = Settings(archive=root, database_url=sqlite_url(root))
    with Archive.create(settings) as archive:
        auth.add_account(archive, "admin-1", role="admin")
        token = auth.create_token(archive, "admin-1")
        archive.add_station("clinic-1")
    headers = {"Authorization": f"Bearer {token}"}
    # serve's private metrics directory is made under TMPDIR: it must be gone afterwards
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    port = free_port()
    base_url = f"http://127.0.0.1:{port}"
    env = os.environ | {"TMPDIR": str(scratch)}
    env.pop("PROMETHEUS_MULTIPROC_DIR", None)
    server = subprocess.Popen(
        [sys.executable, "-m", "rasterserver", "--archive", str(root),
         "--database-url", settings.database_url, "serve", "--host", "127.0.0.1",
         "--port", str(port), "--workers", "2"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    output: list[str] = []
    reader = threading.Thread(target=_collect_output, args=(server.stdout, output), daemon=True)
    reader.start()
    try:
        # both workers up, or the first one would serve every request
        deadline = time.monotonic() + 90
        while sum("Application startup complete" in line for line in output) < 2:
            assert server.poll() is None, "".join(output)
            assert time.monotonic() < deadline, "".join(output)
            time.sleep(0.1)

        def one_request(_i: int) -> int:
            # a fresh connection each time, so the kernel hands them to either worker
            return httpx.get(f"{base_url}/stations/clinic-1", headers=headers,
                             timeout=30).status_code

        n = 60
        with ThreadPoolExecutor(max_workers=8) as pool:
            assert list(pool.map(one_request, range(n))) == [200] * n
        # every scrape, whichever worker answers it, sees all n requests
        for _ in range(6):
            scrape = httpx.get(f"{base_url}/metrics", headers=headers, timeout=30)
            assert scrape.status_code == 200, scrape.text
            samples = _samples(scrape.text)
            assert _requests(samples, "GET", "/stations/{station}", 200) == n, scrape.text
            assert _observed(samples, "GET", "/stations/{station}") == n
            assert "clinic-1" not in scrape.text
    finally:
        server.terminate()
        server.wait(timeout=60)
        reader.join(timeout=10)
    assert list(scratch.iterdir()) == [], "".join(output)
