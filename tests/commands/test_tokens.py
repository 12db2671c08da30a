"""``rasterserver user``, ``token`` and ``keys`` as installed (a fresh process each), on
SQLite and PostgreSQL: tokens expire (default and per token), accounts are disabled and
enabled, every change is in the audit trail with the CLI's actor, bad lifetimes exit 2, the
pseudonym key is rotated only when confirmed."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

from installed_cli import TRACEBACK, describe, run_installed

from rasterserver.archive import Archive
from rasterserver.config import Settings
from rasterserver.pseudonym_key import read_key_file
from rasterserver.services import auth
from rasterserver.services.audit_trail import audit_events


def _run(settings: Settings, *args: str, env: dict[str, str] | None = None):
    done = run_installed(*args, archive=settings.archive, database_url=settings.database_url,
                         env=env)
    assert TRACEBACK not in done.stderr, describe(done)
    return done


def test_expiry_disable_and_audit(settings: Settings) -> None:
    assert _run(settings, "db", "upgrade").returncode == 0
    assert _run(settings, "user", "add", "dr-a", "--role", "clinician").returncode == 0
    made = _run(settings, "token", "create", "dr-a", "--label", "ward")
    assert made.returncode == 0, describe(made)
    token = made.stdout.strip().splitlines()[-1]
    short = _run(settings, "token", "create", "dr-a", "--days", "2")
    assert short.returncode == 0, describe(short)
    env_default = _run(settings, "token", "create", "dr-a",
                       env={"RASTERSERVER_TOKEN_DAYS": "7"})
    assert env_default.returncode == 0, describe(env_default)
    at = _run(settings, "token", "create", "dr-a", "--expires-at", "2099-01-01T00:00Z")
    assert at.returncode == 2 and "3650" in at.stderr  # beyond ten years
    for bad in (["--days", "0"], ["--days", "4000"], ["--expires-at", "2020-01-01T00:00Z"],
                ["--expires-at", "2030-01-01T00:00"], ["--days", "3", "--expires-at",
                                                       "2030-01-01T00:00Z"]):
        refused = _run(settings, "token", "create", "dr-a", *bad)
        assert refused.returncode == 2, describe(refused)
    assert _run(settings, "token", "create", "dr-a",
                env={"RASTERSERVER_TOKEN_DAYS": "x"}).returncode == 2

    now = dt.datetime.now(dt.UTC)
    with Archive(settings) as archive:
        infos = auth.tokens(archive, account="dr-a")
        assert [round((t.expires_at - now).total_seconds() / 86400) for t in infos] == [90, 2, 7]
        assert auth.authenticate(archive, token).name == "dr-a"
    listing = _run(settings, "token", "list").stdout
    assert "active" in listing and "expires " in listing and token not in listing

    assert _run(settings, "user", "disable", "dr-a").returncode == 0
    with Archive(settings) as archive:
        assert auth.authenticate(archive, token) is None
    assert "account disabled" in _run(settings, "token", "list").stdout
    assert "disabled" in _run(settings, "user", "list").stdout
    again = _run(settings, "user", "disable", "dr-a")
    assert again.returncode == 0 and "already" in again.stdout
    assert _run(settings, "user", "disable", "nobody").returncode == 3
    assert _run(settings, "user", "enable", "dr-a").returncode == 0
    with Archive(settings) as archive:
        assert auth.authenticate(archive, token).name == "dr-a"
        # an expired token is refused like a revoked one
        with archive.session() as s:
            row = s.get(auth.ApiToken, infos[0].id)
            row.expires_at = now - dt.timedelta(seconds=1)
        assert auth.authenticate(archive, token) is None
    assert "expired" in _run(settings, "token", "list").stdout
    assert _run(settings, "token", "revoke", str(infos[1].id)).returncode == 0

    with Archive(settings) as archive:
        events = [e for e, _ in audit_events(archive, limit=1000)]
    assert [(e.route, e.action) for e in events] == [
        ("cli: user add", "C"), ("cli: token create", "C"), ("cli: token create", "C"),
        ("cli: token create", "C"), ("cli: user disable", "U"), ("cli: user enable", "U"),
        ("cli: token revoke", "U")]
    assert all(e.actor.startswith("cli:") and e.method == "CLI" for e in events)
    assert "dr-a" in events[0].detail and f"token {infos[0].id}" in events[1].detail
    assert not any(token in e.detail or token[:20] in e.detail for e in events)
    exported = _run(settings, "audit", "export")
    assert json.loads(exported.stdout)["total"] == len(events)


def test_rotate_pseudonyms(settings: Settings, tmp_path: Path) -> None:
    assert _run(settings, "db", "upgrade").returncode == 0
    key_file = settings.archive / "config" / "pseudonym.key"
    with Archive(settings) as archive:
        from rasterserver.services.pseudonyms import Pseudonymiser

        old = Pseudonymiser(archive).key
    unconfirmed = _run(settings, "keys", "rotate-pseudonyms")
    assert unconfirmed.returncode == 2 and "--yes" in unconfirmed.stderr
    assert read_key_file(key_file) == old
    kept = tmp_path / "old.key"
    done = _run(settings, "keys", "rotate-pseudonyms", "--yes", "--keep-old", str(kept))
    assert done.returncode == 0, describe(done)
    assert read_key_file(kept) == old and read_key_file(key_file) not in (None, old)
    assert _run(settings, "keys", "rotate-pseudonyms", "--yes", "--keep-old",
                str(kept)).returncode == 2
    from_env = _run(settings, "keys", "rotate-pseudonyms", "--yes",
                    env={"RASTERSERVER_PSEUDONYM_KEY": "ab" * 16})
    assert from_env.returncode == 2 and "RASTERSERVER_PSEUDONYM_KEY" in from_env.stderr
