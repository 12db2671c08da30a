"""``rasterserver serve`` in a subprocess, and the request limits on their own."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import anyio
import httpx
from api_helpers import free_port
from fastapi import FastAPI

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


#: the installed console script, beside the interpreter running the tests
RASTERSERVER = str(Path(sys.executable).with_name("rasterserver"))


def _serve(archive: Path, *args: str, env: dict[str, str] | None = None,
           database_url: str | None = None) -> tuple[subprocess.Popen[bytes], int]:
    """Start the installed ``rasterserver serve`` in a session of its own; (process, port)."""
    port = free_port()
    where = ["--archive", str(archive)] + (["--database-url", database_url] if database_url
                                          else [])
    server = subprocess.Popen([RASTERSERVER, *where, "serve", "--port", str(port), *args],
                              env=os.environ | (env or {}), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, start_new_session=True)
    return server, port


def _healthy(server: subprocess.Popen[bytes], port: int) -> dict:
    """Wait for /health to answer and return it; fail with the server's output if it stops."""
    deadline = time.monotonic() + 90
    while True:
        try:
            return httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).json()
        except httpx.TransportError:
            if server.poll() is not None:
                raise AssertionError(server.stdout.read().decode()) from None
            assert time.monotonic() < deadline, "the server did not answer"
            time.sleep(0.2)


def test_the_first_serve_creates_a_new_sqlite_catalogue(tmp_path: Path) -> None:
    archive = tmp_path / "archive"  # nothing there yet: no `db upgrade`
    server, port = _serve(archive)
    try:
        health = _healthy(server, port)
        engine = make_engine(sqlite_url(archive))
        assert health["schema_revision"] == migrate.head_revision(engine)
        assert migrate.current_revision(engine) == migrate.head_revision(engine)
        engine.dispose()
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        output = server.communicate(timeout=60)[0].decode()
    assert "created the catalogue" in output
    # the second start finds it and creates nothing
    server, port = _serve(archive)
    try:
        _healthy(server, port)
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        assert "created the catalogue" not in server.communicate(timeout=60)[0].decode()


def test_serve_leaves_an_empty_postgresql_catalogue_to_the_operator(
        tmp_path: Path, postgres_url: str) -> None:
    done = subprocess.run([RASTERSERVER, "--archive", str(tmp_path / "archive"),
                           "--database-url", postgres_url, "serve"],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 6, done.stderr
    assert "rasterserver db upgrade" in done.stderr and "Traceback" not in done.stderr
    engine = make_engine(postgres_url)
    assert migrate.current_revision(engine) is None
    engine.dispose()


def test_a_killed_server_leaves_no_metrics_folder_behind(tmp_path: Path) -> None:
    temp = tmp_path / "tmp"
    temp.mkdir()
    env = {"TMPDIR": str(temp)}
    archive = tmp_path / "archive"
    server, port = _serve(archive, "--workers", "2", env=env)
    _healthy(server, port)
    (first,) = temp.glob("rasterserver-metrics-*")
    os.killpg(server.pid, signal.SIGKILL)  # the server and its workers, no clean-up
    server.communicate(timeout=60)
    assert first.is_dir()
    server, port = _serve(archive, "--workers", "2", env=env)
    try:
        _healthy(server, port)
        assert not first.exists()
        assert len(list(temp.glob("rasterserver-metrics-*"))) == 1
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.communicate(timeout=60)
    assert list(temp.glob("rasterserver-metrics-*")) == []


def test_timeouts_and_chunked_bodies_get_json_errors(serve_app) -> None:
    """Over a real connection to uvicorn on loopback: a chunked body has no length for the
    limit to read beforehand."""
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
    with httpx.Client(base_url=serve_app(app), timeout=30) as client:
        late = client.get("/slow")
        assert late.status_code == 504 and late.json()["error"] == "Timeout"

        def chunks():
            yield b'{"a": "'
            yield b"x" * 200
            yield b'"}'

        big = client.post("/echo", content=chunks(), headers={"content-type": "application/json"})
        assert big.status_code == 413 and big.json()["error"] == "PayloadTooLarge"
        assert client.post("/echo", json={"a": "b"}).json() == {"a": "b"}
