"""``rasterserver verify --repair`` / ``--dry-run`` through the CLI, on SQLite and PostgreSQL."""

from __future__ import annotations

import hashlib
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from rasterserver.archive import Archive, FrameSource
from rasterserver.cli import main
from rasterserver.config import Settings
from rasterserver.store.raw import FrameToWrite


class _Crash(BaseException):
    """Stops a write like a crash: not an ``Exception``, so the store does not clean up."""


@pytest.fixture
def cli(cli: Callable[..., int]) -> Callable[..., int]:
    """The commands' ``cli``, with patient P7 registered."""
    assert cli("patient", "add", "P7") == 0
    return cli


def _files(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*"))
            if p.is_file() and not p.name.startswith("catalog.sqlite")}


def _leftovers(settings: Settings, tmp_path: Path) -> tuple[Path, Path]:
    """A temporary and an orphaned raw file, as crashes leave them; and one good ingest."""
    frame = tmp_path / "f.npy"
    np.save(frame, np.random.default_rng(5).integers(0, 256, (32, 32), np.uint8))

    def hook(step: str) -> None:
        if step == "fsynced":
            raise _Crash

    with Archive(settings) as archive:
        archive.ingest([FrameSource(frame)], patient="P7")
        uid = uuid.uuid4().hex  # published, then the process "died" before the commit
        archive.raw.write(uid, [FrameToWrite(0, "raster", np.ones((8, 8), np.uint8))])
        orphan = archive.raw.path_for(uid)
    with Archive(settings, crash_hook=hook) as crashing, pytest.raises(_Crash):
        crashing.ingest([FrameSource(frame)], patient="P7")
    (temp,) = (settings.archive / "raw").rglob("*.tmp-*")
    return temp, orphan


def test_dry_run_then_repair(
    cli, settings: Settings, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    temp, orphan = _leftovers(settings, tmp_path)
    before = _files(settings.archive)
    capsys.readouterr()

    assert cli("verify", "--dry-run", "--min-age", "0") == 5  # nothing changed: still broken
    out = capsys.readouterr()
    assert "would delete\ttemporary" in out.out and "would quarantine\torphaned" in out.out
    assert out.out.splitlines()[-1].startswith("dry run, nothing changed: would delete 1")
    assert "dry run" in out.err
    assert _files(settings.archive) == before

    assert cli("verify", "--repair") == 5  # default --min-age 60: too young to touch
    assert "deferred" in capsys.readouterr().out
    assert _files(settings.archive) == before

    assert cli("verify", "--repair", "--min-age", "0") == 0
    out = capsys.readouterr().out
    last = out.splitlines()[-1]
    assert last.startswith("repair: deleted 1 temporary file(s), quarantined 1 orphaned")
    assert not temp.exists() and not orphan.exists()
    moved = next((settings.archive / "quarantine").rglob(orphan.name))
    assert hashlib.sha256(moved.read_bytes()).hexdigest() == before[
        orphan.relative_to(settings.archive).as_posix()]
    assert (moved.parents[3] / "manifest.json").is_file()

    after = _files(settings.archive)
    assert cli("verify") == 0
    assert cli("verify", "--repair", "--min-age", "0") == 0  # a second repair: nothing to do
    assert capsys.readouterr().out.splitlines()[-1].endswith(": OK")
    assert _files(settings.archive) == after


def test_repair_exits_5_when_something_needs_a_person(
    cli, settings: Settings, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    temp, orphan = _leftovers(settings, tmp_path)
    good = next(p for p in (settings.archive / "raw").rglob("*.h5") if p != orphan)
    good.unlink()  # a row without its file: restore from backup
    stray = temp.parent / "README.txt"
    stray.write_text("not ours")
    capsys.readouterr()

    assert cli("verify", "--repair", "--min-age", "0") == 5
    out = capsys.readouterr()
    assert "needs a person\tmissing" in out.out and "from backup" in out.out
    assert "left alone\tstray" in out.out
    assert out.out.splitlines()[-1] == (
        "repair: deleted 1 temporary file(s), quarantined 1 orphaned file(s) into quarantine/"
        f"{next((settings.archive / 'quarantine').iterdir()).name}, 1 stray file(s) left "
        "alone, 1 need(s) a person (restore from backup)")
    assert "2 problem(s) remain" in out.err
    assert stray.read_text() == "not ours" and not temp.exists()


def test_damaged_stored_results_are_reported_not_touched(
    cli, settings: Settings, processed: str, capsys: pytest.CaptureFixture[str]
) -> None:
    derived = sorted((settings.archive / "derived").rglob("*.h5"))
    derived[0].unlink()
    before = _files(settings.archive)
    capsys.readouterr()

    assert cli("verify", "--repair", "--min-age", "0") == 5
    out = capsys.readouterr().out
    assert "needs a person\tmissing" in out and "rasterserver process" in out
    assert _files(settings.archive) == before  # the raw frame and the other results unchanged


def test_min_age_needs_repair(cli, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli("verify", "--min-age", "5") == 2
    assert "--repair" in capsys.readouterr().err


def test_help_explains_repair(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["verify", "--help"]) == 0
    out = capsys.readouterr().out
    for word in ("--repair", "--dry-run", "--min-age", "quarantine", "never touched"):
        assert word in out
