"""Authentication before the body (rasterserver.api.gate), on a real uvicorn server on
loopback (SQLite and PostgreSQL): a 250 MB upload without a valid token, or with the token
of a role that may not upload, is answered 401/403 while the client has sent its headers
only; a valid token's upload is waited for (the server does read bodies it is entitled to)."""

from __future__ import annotations

import socket
import time
from urllib.parse import urlsplit

import pytest
from api_helpers import PATIENT_ID, LiveServer, frame, npy_bytes

from rasterserver.api.app import ApiSettings
from rasterserver.services.audit_trail import audit_events

BIG = 250 * 1024 * 1024


@pytest.fixture
def big_live(start_server, settings) -> LiveServer:
    """A live server that accepts uploads of 300 MB (so 250 MB is not a 413)."""
    return start_server(settings, ApiSettings(max_upload_bytes=300 * 1024 * 1024))


def _headers_only(live: LiveServer, token: str | None, *, path: str = "/acquisitions",
                  chunked: bool = False, wait_s: float = 10.0) -> tuple[bytes, int]:
    """Send the headers of a 250 MB multipart upload and a first 64 KiB of its body, never
    the rest; return what the server answered within ``wait_s`` (b"" if nothing) and how
    many body bytes were sent."""
    where = urlsplit(live.url)
    lines = [f"POST {path} HTTP/1.1", f"Host: {where.netloc}",
             "Content-Type: multipart/form-data; boundary=xyz"]
    lines.append("Transfer-Encoding: chunked" if chunked else f"Content-Length: {BIG}")
    if token is not None:
        lines.append(f"Authorization: Bearer {token}")
    head = ("\r\n".join(lines) + "\r\n\r\n").encode()
    first = b"--xyz\r\nContent-Disposition: form-data; name=\"files\"; filename=\"a.npy\"\r\n\r\n"
    first += b"\0" * (64 * 1024 - len(first))
    if chunked:
        first = f"{len(first):x}\r\n".encode() + first + b"\r\n"
    with socket.create_connection((where.hostname, where.port), timeout=wait_s) as sock:
        sock.sendall(head + first)
        answer = b""
        deadline = time.monotonic() + wait_s
        try:
            while b"\r\n\r\n" not in answer and time.monotonic() < deadline:
                chunk = sock.recv(65536)
                if not chunk:
                    break
                answer += chunk
        except TimeoutError:
            pass
    return answer, len(first)


def test_an_upload_without_a_valid_token_is_refused_before_its_body(big_live: LiveServer) -> None:
    started = time.monotonic()
    answer, sent = _headers_only(big_live, None)
    assert answer.startswith(b"HTTP/1.1 401"), answer[:200]
    assert sent < BIG // 1000 and time.monotonic() - started < 10
    head = answer.lower()
    assert b"www-authenticate: bearer" in head and b"connection: close" in head

    for token in ("rs_" + "x" * 43, "not-a-token"):
        answer, _ = _headers_only(big_live, token)
        assert answer.startswith(b"HTTP/1.1 401"), answer[:200]
    answer, _ = _headers_only(big_live, None, chunked=True)  # no length to judge it by
    assert answer.startswith(b"HTTP/1.1 401"), answer[:200]

    # a role that may not upload: 403, also before the body
    answer, _ = _headers_only(big_live, big_live.tokens["researcher"])
    assert answer.startswith(b"HTTP/1.1 403"), answer[:200]
    # another route with a body: the same
    answer, _ = _headers_only(big_live, None, path="/patients")
    assert answer.startswith(b"HTTP/1.1 401"), answer[:200]

    # refusals are audited, with the route they were for
    with big_live.archive() as archive:
        events = audit_events(archive, limit=1000)
    refused = [e for e, _ in events if e.route == "/acquisitions" and e.method == "POST"]
    assert [e.status for e in refused] == [401, 401, 401, 401, 403]
    assert refused[-1].actor == "researcher-1"


def test_an_entitled_upload_is_read(big_live: LiveServer) -> None:
    # the station may upload: the server waits for the rest of the body, as it should
    answer, _ = _headers_only(big_live, big_live.tokens["station"], wait_s=2.0)
    assert answer == b""
    # and a small upload with a valid token still works end to end through the gate
    with big_live.client("station") as cam:
        stored = cam.post("/acquisitions", files=[("files", ("a.npy", npy_bytes(frame())))],
                          data={"patient": PATIENT_ID})
        assert stored.status_code == 201, stored.text
