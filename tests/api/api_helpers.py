"""Helpers of the API tests: a live server handle, test frames, the patient under test."""

from __future__ import annotations

import io
import socket
import time
from dataclasses import dataclass, field

import httpx
import numpy as np

from rasterserver.archive import Archive
from rasterserver.config import Settings

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


def npy_bytes(array: np.ndarray) -> bytes:
    """``array`` as the bytes of an .npy file."""
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def frame(seed: int = 0, dtype: type = np.uint8) -> np.ndarray:
    """A 604x576 test frame."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 200, (604, 576)).astype(dtype)


def run_job(client: httpx.Client, uids: list[str], **body: object) -> dict:
    """Post a processing job (the default targets unless ``body`` says otherwise) and wait
    until it is done; return its final state."""
    job = client.post("/jobs", json={"uids": uids, **body})
    assert job.status_code == 202, job.text
    deadline = time.monotonic() + 300
    while (state := client.get(f"/jobs/{job.json()['id']}").json())["status"] in (
        "queued",
        "running",
    ):
        assert time.monotonic() < deadline
        time.sleep(0.3)
    assert state["status"] == "done", state
    return state
