"""A real uvicorn server on loopback for the API tests, with one account per role."""

from __future__ import annotations

import io
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
import pytest
import uvicorn

from rasterserver.api import auth
from rasterserver.api.app import ApiSettings, create_app
from rasterserver.archive import Archive
from rasterserver.config import Settings, sqlite_url

ROLES = ("admin", "clinician", "station", "researcher")
# patient data that must never reach the application log
PATIENT_ID = "MRN-0047113"
PATIENT_NAME = "Erika Mustermann"


def free_port() -> int:
    """A TCP port free on loopback right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class LiveServer:
    """A running server: its base URL, a token per role, and the archive behind it."""

    url: str
    settings: Settings
    tokens: dict[str, str] = field(default_factory=dict)

    def client(self, role: str | None = None, *, token: str | None = None) -> httpx.Client:
        """An httpx client, authenticated as ``role`` or with ``token`` (neither: none)."""
        token = token or (self.tokens[role] if role else None)
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=60)

    def archive(self) -> Archive:
        """A second handle on the archive, to check what the server stored."""
        return Archive(self.settings)


@pytest.fixture
def start_server() -> Iterator:
    """Start a server for given settings; stopped at the end of the test."""
    running: list[tuple[uvicorn.Server, threading.Thread]] = []

    def start(settings: Settings, api: ApiSettings | None = None) -> LiveServer:
        with Archive.create(settings) as archive:
            tokens = {}
            for role in ROLES:
                auth.add_account(archive, f"{role}-1", role=role,
                                 kind="service" if role == "station" else "user")
                tokens[role] = auth.create_token(archive, f"{role}-1")
            archive.add_patient(PATIENT_ID, name=PATIENT_NAME)
            archive.add_station("clinic-1")
        port = free_port()
        app = create_app(settings, api or ApiSettings(max_upload_bytes=8 * 1024 * 1024))
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
        running.append((server, thread))
        return LiveServer(f"http://127.0.0.1:{port}", settings, tokens)

    yield start
    for server, thread in running:
        server.should_exit = True
        thread.join(timeout=30)


@pytest.fixture
def live(start_server, settings: Settings) -> LiveServer:
    """A live server on both catalogue backends (SQLite, PostgreSQL)."""
    return start_server(settings)


@pytest.fixture
def live_sqlite(start_server, tmp_path: Path) -> LiveServer:
    """A live server on SQLite only (for the slower or wider walks)."""
    root = tmp_path / "archive"
    return start_server(Settings(archive=root, database_url=sqlite_url(root)))


def npy_bytes(array: np.ndarray) -> bytes:
    """``array`` as the bytes of an .npy file."""
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def frame(seed: int = 0, dtype: type = np.uint8) -> np.ndarray:
    """A 604x576 test frame."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 200, (604, 576)).astype(dtype)
