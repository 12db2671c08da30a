"""Pseudonyms, tokens and the audit export, without a server: the services and the CLI."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest

from rasterserver.archive import Archive
from rasterserver.catalog.auth_models import ApiToken
from rasterserver.cli import main
from rasterserver.config import Settings, sqlite_url
from rasterserver.errors import ConflictError, InputError, NotFoundError
from rasterserver.services import auth
from rasterserver.services.audit import AuditNote, write_events
from rasterserver.services.pseudonyms import MAX_SHIFT_DAYS, Pseudonymiser, load_key


@pytest.fixture
def archive(tmp_path: Path) -> Archive:
    root = tmp_path / "archive"
    with Archive.create(Settings(archive=root, database_url=sqlite_url(root))) as a:
        yield a


def test_pseudonyms_are_stable_keyed_and_reversible_only_with_the_key(archive: Archive,
                                                                      monkeypatch) -> None:
    monkeypatch.delenv("RASTERSERVER_PSEUDONYM_KEY", raising=False)
    for i in range(50):
        archive.add_patient(f"P{i}")
    one, two = Pseudonymiser(archive), Pseudonymiser(archive)
    assert load_key(archive) == one.key == two.key  # made once, kept in the key file
    key_file = archive.settings.archive / "config" / "pseudonym.key"
    assert bytes.fromhex(key_file.read_text()) == one.key
    assert key_file.stat().st_mode & 0o777 == 0o600
    names = {one.pseudonym(f"P{i}") for i in range(50)}
    assert len(names) == 50 and names == {two.pseudonym(f"P{i}") for i in range(50)}
    assert not any(f"P{i}" in n for i, n in enumerate(sorted(names)))
    other = Pseudonymiser(archive, key=b"k" * 32)
    assert other.pseudonym("P1") != one.pseudonym("P1")
    assert one.identifier(one.pseudonym("P7")) == "P7"
    with pytest.raises(NotFoundError):
        one.identifier(other.pseudonym("P7"))
    shifts = [one.shift_days(f"P{i}") for i in range(50)]
    assert all(-MAX_SHIFT_DAYS <= s <= MAX_SHIFT_DAYS for s in shifts)
    assert len(set(shifts)) > 40  # per patient, not one global offset
    a, b = dt.date(2024, 1, 31), dt.date(2024, 8, 2)
    assert one.shift_date("P3", b) - one.shift_date("P3", a) == b - a
    monkeypatch.setenv("RASTERSERVER_PSEUDONYM_KEY", "ab" * 16)
    assert load_key(archive) == bytes.fromhex("ab" * 16)
    monkeypatch.setenv("RASTERSERVER_PSEUDONYM_KEY", "zz")
    with pytest.raises(InputError):
        load_key(archive)


def test_tokens_are_stored_as_digests_only(archive: Archive) -> None:
    auth.add_account(archive, "dr-who", role="clinician")
    with pytest.raises(ConflictError):
        auth.add_account(archive, "dr-who", role="clinician")
    with pytest.raises(InputError):
        auth.add_account(archive, "x", role="superuser")
    token = auth.create_token(archive, "dr-who")
    with archive.session() as s:
        row = s.query(ApiToken).one()
    assert token not in (row.token_sha256, row.prefix) and row.token_sha256 == \
        auth.token_digest(token)
    assert auth.authenticate(archive, token).role == "clinician"
    assert auth.authenticate(archive, token + "x") is None
    with pytest.raises(NotFoundError):
        auth.create_token(archive, "nobody")


def test_cli_users_tokens_and_fhir_audit_export(archive: Archive, tmp_path: Path,
                                                capsys) -> None:
    base = ["--archive", str(archive.settings.archive),
            "--database-url", archive.settings.database_url]
    assert main([*base, "user", "add", "root", "--role", "admin"]) == 0
    assert main([*base, "token", "create", "root"]) == 0
    token = capsys.readouterr().out.strip().splitlines()[-1]
    assert token.startswith("rs_")
    assert main([*base, "token", "create", "cam-2", "--service-account"]) == 0
    capsys.readouterr()
    assert main([*base, "token", "list"]) == 0
    listing = capsys.readouterr().out
    assert token not in listing and "cam-2\tstation" in listing and "active" in listing
    assert main([*base, "token", "revoke", "1"]) == 0
    assert auth.authenticate(archive, token) is None
    assert main([*base, "token", "revoke", "99"]) == 3
    archive.add_patient("P-1")
    note = AuditNote(principal=auth.Principal(1, "root", "admin", "user"))
    note.touch(archive.patient("P-1").id, "a" * 32)
    write_events(archive, note, method="GET", route="/acquisitions/{uid}",
                 route_name="get_acquisition", status=200, client="127.0.0.1")
    out = tmp_path / "audit.json"
    assert main([*base, "audit", "export", "-o", str(out), "--patient", "P-1"]) == 0
    bundle = json.loads(out.read_text())
    (entry,) = bundle["entry"]
    event = entry["resource"]
    assert event["resourceType"] == "AuditEvent" and event["action"] == "R"
    assert event["recorded"].endswith("+00:00")
    assert event["entity"][0]["what"]["identifier"]["value"] == "P-1"


def test_a_job_whose_process_is_gone_reports_failed(archive: Archive) -> None:
    import socket

    from rasterserver.catalog.job_models import ProcessingJob
    from rasterserver.services.jobs import JobRunner

    with archive.session() as s:
        s.add(ProcessingJob(id="a" * 32, origin="http", owner="x", selection={"uids": ["u"]},
                            chain={}, targets=["mesh"], engine="", state="running", total=1,
                            done=0, failed=0, resumed_count=0, error="",
                            runner=f"{socket.gethostname()}:{2**22 + 12345}"))
    runner = JobRunner(archive)
    try:
        job = runner.get("a" * 32)
        # stored as it was (resumable), reported as interrupted
        assert job.interrupted and job.state == "interrupted" and job.job.state == "running"
        assert [j.job.id for j in runner.list(status="running")] == ["a" * 32]
        with pytest.raises(NotFoundError):
            runner.get("b" * 32)
    finally:
        runner.close()


def test_pseudonyms_of_patients_registered_later_resolve(archive: Archive, monkeypatch) -> None:
    monkeypatch.delenv("RASTERSERVER_PSEUDONYM_KEY", raising=False)
    archive.add_patient("P-1")
    names = Pseudonymiser(archive)
    assert names.identifier(names.pseudonym("P-1")) == "P-1"
    archive.add_patient("P-2")  # after the first look-up filled the table
    assert names.identifier(names.pseudonym("P-2")) == "P-2"
    for _ in range(3):
        with pytest.raises(NotFoundError):
            names.identifier("PS-" + "0" * 20)
    assert names.identifier(names.pseudonym("P-1")) == "P-1"


def test_warming_fills_the_table_before_the_first_look_up(archive: Archive,
                                                          monkeypatch) -> None:
    monkeypatch.delenv("RASTERSERVER_PSEUDONYM_KEY", raising=False)
    for i in range(20):
        archive.add_patient(f"P-{i}")
    names = Pseudonymiser(archive)
    names.warm()
    calls = []
    monkeypatch.setattr(names, "_patients_after", lambda after: calls.append(after) or [])
    assert names.identifier(names.pseudonym("P-7")) == "P-7" and calls == []
