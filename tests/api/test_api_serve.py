"""``rasterserver serve`` in a subprocess, and the request limits on their own."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import anyio
import httpx
from api_helpers import free_port
from fastapi import FastAPI
from fastapi.testclient import TestClient

from rasterserver.api.errors import LimitsMiddleware, install_handlers
from rasterserver.catalog import migrate
from rasterserver.catalog.database import make_engine
from rasterserver.config import sqlite_url


def test_serve_command_runs_uvicorn_on_loopback(tmp_path: Path) -> None:
    archive = tmp_path / "archive"
    base = [sys.executable, "-m", "rasterserver", "--archive", str(archive)]
    subprocess.run([*base, "db", "upgrade"], check=True, capture_output=True)
    port = free_port()
    env = os.environ | {"RASTERSERVER_PORT": str(port)}
    server = subprocess.Popen([*base, "serve", "--host", "127.0.0.1"], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                health = httpx.get(f"http://127.0.0.1:{port}/health", timeout=2)
                break
            except httpx.TransportError:
                assert server.poll() is None, server.stdout.read().decode()
                assert time.monotonic() < deadline
                time.sleep(0.2)
        engine = make_engine(sqlite_url(archive))
        assert health.json()["schema_revision"] == migrate.head_revision(engine)
        engine.dispose()
        assert httpx.get(f"http://127.0.0.1:{port}/patients").status_code == 401
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_timeouts_and_chunked_bodies_get_json_errors() -> None:
    app = FastAPI()
    install_handlers(app)

    @app.get("/slow")
    async def slow() -> dict[str, str]:
        await anyio.sleep(5)
        return {"never": "sent"}

    @app.post("/echo")
    async def echo(body: dict[str, str]) -> dict[str, str]:
        return body

    app.add_middleware(LimitsMiddleware, max_body_bytes=100, timeout_s=0.2)
    with TestClient(app) as client:
        late = client.get("/slow")
        assert late.status_code == 504 and late.json()["error"] == "Timeout"

        def chunks():
            yield b'{"a": "'
            yield b"x" * 200
            yield b'"}'

        big = client.post("/echo", content=chunks(), headers={"content-type": "application/json"})
        assert big.status_code == 413 and big.json()["error"] == "PayloadTooLarge"
        assert client.post("/echo", json={"a": "b"}).json() == {"a": "b"}
