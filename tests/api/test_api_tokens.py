"""Token expiry and disabled accounts over HTTP, on a live server (SQLite, and PostgreSQL with
its token cache): an expired token is refused even while its owner is cached, a disabled
account's tokens are refused until it is enabled, and an account made over HTTP is named in
its audit event."""

from __future__ import annotations

import datetime as dt
import time
from collections.abc import Callable

from api_helpers import LiveServer

from rasterserver.services import auth
from rasterserver.services.audit_trail import audit_events


def until(check: Callable[[], bool], timeout: float = 10.0) -> bool:
    """Whether ``check`` holds within ``timeout`` s (the cache hears of changes by NOTIFY)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(0.05)
    return check()


def test_expiry_and_disabled_accounts(live: LiveServer) -> None:
    with live.archive() as archive:
        soon = auth.create_token(archive, "clinician-1",
                                 expires_at=dt.datetime.now(dt.UTC) + dt.timedelta(seconds=3))
    with live.client(token=soon) as c:
        assert c.get("/patients").status_code == 200  # cached from here on (PostgreSQL)
        assert until(lambda: c.get("/patients").status_code == 401, timeout=15)
        refused = c.get("/patients")
        assert "expired" in refused.json()["detail"]

    with live.client("clinician") as c:
        assert c.get("/patients").status_code == 200
        with live.archive() as archive:
            assert auth.set_account_disabled(archive, "clinician-1", True)
        assert until(lambda: c.get("/patients").status_code == 401)
        # refused before an upload's body too (the gate)
        assert c.post("/patients", json={"identifier": "X-1"}).status_code == 401
        with live.archive() as archive:
            assert auth.set_account_disabled(archive, "clinician-1", False)
            assert not auth.set_account_disabled(archive, "clinician-1", False)
        assert until(lambda: c.get("/patients").status_code == 200)

    with live.client("admin") as a:
        made = a.post("/accounts", json={"name": "dr-new", "role": "researcher"})
        assert made.status_code == 201, made.text
    with live.archive() as archive:
        (event,) = [e for e, _ in audit_events(archive, limit=1000)
                    if e.route == "/accounts" and e.method == "POST"]
    assert event.actor == "admin-1" and "dr-new" in event.detail and "researcher" in event.detail
