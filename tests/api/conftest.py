"""A real uvicorn server on loopback for the API tests, with one account per role."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import uvicorn
from api_helpers import PATIENT_ID, PATIENT_NAME, ROLES, LiveServer, free_port

from rasterserver.api.app import ApiSettings, create_app
from rasterserver.archive import Archive
from rasterserver.config import Settings, sqlite_url
from rasterserver.services import auth


def _uvicorn(app: Any) -> tuple[str, uvicorn.Server, threading.Thread]:
    """Serve ``app`` with uvicorn on a free loopback port in a thread; its URL, once up."""
    port = free_port()
    config = uvicorn.Config(app, host="127.0.0.1", port=port, log_config=None,
                            access_log=False, lifespan="on")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    return f"http://127.0.0.1:{port}", server, thread


@pytest.fixture
def serve_app() -> Iterator[Callable[[Any], str]]:
    """Serve any ASGI app on loopback (``serve_app(app)`` gives its URL); stopped at the end
    of the test."""
    running: list[tuple[uvicorn.Server, threading.Thread]] = []

    def start(app: Any) -> str:
        url, server, thread = _uvicorn(app)
        running.append((server, thread))
        return url

    yield start
    for server, thread in running:
        server.should_exit = True
        thread.join(timeout=30)


@pytest.fixture
def start_server(serve_app: Callable[[Any], str]) -> Callable[..., LiveServer]:
    """Start a server for given settings; stopped at the end of the test."""

    def start(settings: Settings, api: ApiSettings | None = None) -> LiveServer:
        with Archive.create(settings) as archive:
            tokens = {}
            for role in ROLES:
                auth.add_account(archive, f"{role}-1", role=role,
                                 kind="service" if role == "station" else "user")
                tokens[role] = auth.create_token(archive, f"{role}-1")
            archive.add_patient(PATIENT_ID, name=PATIENT_NAME)
            archive.add_station("clinic-1")
        app = create_app(settings, api or ApiSettings(max_upload_bytes=8 * 1024 * 1024))
        return LiveServer(serve_app(app), settings, tokens)

    return start


@pytest.fixture
def live(start_server, settings: Settings) -> LiveServer:
    """A live server on both catalogue backends (SQLite, PostgreSQL)."""
    return start_server(settings)


@pytest.fixture
def live_sqlite(start_server, tmp_path: Path) -> LiveServer:
    """A live server on SQLite only (for the slower or wider walks)."""
    root = tmp_path / "archive"
    return start_server(Settings(archive=root, database_url=sqlite_url(root)))
