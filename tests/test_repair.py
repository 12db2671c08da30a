"""``Archive.repair``: crash leftovers are cleaned up, and nothing that might matter is lost.

Leftovers are made the way a crash makes them: a real process killed between durable steps
(as in test_archive_crash.py), or the store's own writer stopped by a hook, on SQLite and
PostgreSQL.
"""

from __future__ import annotations

import datetime as dt
import fcntl
import hashlib
import json
import os
import subprocess
import sys
import textwrap
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np
import pytest

from rasterserver import repair as repair_module
from rasterserver.archive import Archive, FrameSource, Problem, VerifyReport
from rasterserver.catalog.models import Acquisition, Frame
from rasterserver.config import Settings
from rasterserver.errors import ConflictError
from rasterserver.pipeline import Pipeline
from rasterserver.records import Image
from rasterserver.repair import MANIFEST, RepairReport
from rasterserver.store.raw import FrameToWrite

NOW = dt.timedelta(0)  # min_age for leftovers made a moment ago

# Like test_archive_crash.SCRIPT, plus a mode that pauses at the step instead of dying:
# the ingest then finishes (commits its row) when the test creates the "go" file.
SCRIPT = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path
    from rasterserver.archive import Archive, FrameSource
    from rasterserver.config import Settings

    archive_dir, url, frame, step, pause = sys.argv[1:6]

    def hook(name):
        if name != step:
            return
        if pause == "-":
            os._exit(137)  # as abrupt as SIGKILL: no cleanup, no flush
        Path(pause + ".reached").touch()
        while not Path(pause + ".go").exists():
            time.sleep(0.05)

    archive = Archive(Settings(archive=Path(archive_dir), database_url=url), crash_hook=hook)
    archive.ingest([FrameSource(Path(frame))], patient="P001")
    """
)


class _Crash(BaseException):
    """Stops a write like a crash: not an ``Exception``, so the store does not clean up."""


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _snapshot(root: Path) -> dict[str, str]:
    """Every file of the archive and its hash, except the SQLite catalogue's own files."""
    return {p.relative_to(root).as_posix(): _sha(p) for p in sorted(root.rglob("*"))
            if p.is_file() and not p.name.startswith("catalog.sqlite")}


def _frame_file(tmp_path: Path, seed: int = 7) -> Path:
    path = tmp_path / f"frame{seed}.npy"
    np.save(path, np.random.default_rng(seed).integers(0, 256, (64, 48), dtype=np.uint8))
    return path


def _start_ingest(settings: Settings, frame: Path, step: str, pause: str = "-"
                  ) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", SCRIPT, str(settings.archive), settings.database_url,
         str(frame), step, pause],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )


def _crash_ingest(settings: Settings, frame: Path, step: str) -> None:
    """Run an ingest in a real process and kill it right after ``step``."""
    process = _start_ingest(settings, frame, step)
    _out, err = process.communicate(timeout=120)
    assert process.returncode == 137, err


def _temp_left_in_process(settings: Settings, frame: Path) -> None:
    """An ingest stopped after fsyncing its temporary file, as a crash stops it."""

    def hook(step: str) -> None:
        if step == "fsynced":
            raise _Crash

    with Archive(settings, crash_hook=hook) as archive, pytest.raises(_Crash):
        archive.ingest([FrameSource(frame)], patient="P001")


def _orphan(archive: Archive, seed: int = 3) -> str:
    """A published raw file without its row: what an ingest leaves if it dies before commit."""
    uid = uuid.uuid4().hex
    pixels = np.random.default_rng(seed).integers(0, 256, (32, 40), dtype=np.uint8)
    archive.raw.write(uid, [FrameToWrite(0, "raster", pixels)])
    return uid


def _verify(archive: Archive) -> VerifyReport:
    raw = archive.verify()
    derived = Pipeline(archive).verify()
    return VerifyReport(problems=[*raw.problems, *derived.problems])


@pytest.fixture
def archive(settings: Settings) -> Iterator[Archive]:
    with Archive.create(settings) as opened:
        opened.add_patient("P001")
        yield opened


def test_crash_leftovers_are_cleaned_up_and_nothing_else_changes(
    archive: Archive, settings: Settings, tmp_path: Path
) -> None:
    root = settings.archive
    kept = archive.ingest([FrameSource(_frame_file(tmp_path, 1))], patient="P001")
    kept_path = archive.raw.path_for(kept.uid)
    kept_hash = _sha(kept_path)
    _crash_ingest(settings, _frame_file(tmp_path, 2), "fsynced")  # a temporary file
    _crash_ingest(settings, _frame_file(tmp_path, 3), "renamed")  # an orphaned file
    # the derived store's leftovers, named as it names them
    derived = Pipeline(archive).derived
    orphan_uid = uuid.uuid4().hex
    stored = derived.write(
        orphan_uid, Image(np.zeros((8, 8), np.uint8)), stage="peaks", plugin="p",
        plugin_version="1", params={}, params_hash="0" * 64, chain_key="a" * 64,
        input_checksum="",
    )
    derived_orphan = root / stored.path
    derived_temp = derived_orphan.with_name(derived_orphan.name + ".tmp-99-0badcafe")
    derived_temp.write_bytes(b"half a result")
    stray = kept_path.parent / "notes.txt"
    stray.write_text("a clinician's note, not ours")
    before = _snapshot(root)

    report = _verify(archive)
    kinds = sorted(p.kind for p in report.problems)
    assert kinds == ["orphaned", "orphaned", "stray", "temporary", "temporary"]
    raw_orphan = next(p for p in report.problems if p.kind == "orphaned" and p.uid != orphan_uid)
    temps = [p.path for p in report.problems if p.kind == "temporary"]

    done = archive.repair(report, min_age=NOW)

    assert sorted(a.action for a in done.actions) == [
        "deleted", "deleted", "left", "quarantined", "quarantined"]
    assert all(not path.exists() for path in temps if path)
    # orphans: moved, byte for byte, into the quarantine with their manifest
    assert done.quarantine is not None and done.quarantine.parent == root / "quarantine"
    assert done.quarantine.name == dt.datetime.now(dt.UTC).strftime("%Y-%m-%d")
    manifest = json.loads((done.quarantine / MANIFEST).read_text())
    assert manifest["format"] == "rasterserver-quarantine"
    entries = {e["original"]: e for e in manifest["entries"]}
    assert set(entries) == {raw_orphan.path.relative_to(root).as_posix(), stored.path}
    for original, entry in entries.items():
        assert not (root / original).exists()
        moved = done.quarantine / entry["quarantined"]
        assert _sha(moved) == before[original] == entry["sha256"]
        assert moved.stat().st_size == entry["size"]
        assert "P001" not in json.dumps(entry)  # uids only, no patient data
    with h5py.File(done.quarantine / entries[raw_orphan.path.relative_to(root).as_posix()]
                   ["quarantined"], "r") as h5:  # still a complete raw file, ready to re-ingest
        assert h5.attrs["uid"] == raw_orphan.uid and "0" in h5["frames"]
    # untouched: the committed acquisition and the stray file
    assert _sha(kept_path) == kept_hash
    assert stray.read_text() == "a clinician's note, not ours"
    assert [a.kind for a in done.remaining] == ["stray"] and not done.ok
    assert "deleted 2 temporary" in done.summary() and "quarantined 2 orphaned" in done.summary()

    # and a second run does nothing
    after = _snapshot(root)
    again = archive.repair(_verify(archive), min_age=NOW)
    assert [(a.action, a.kind) for a in again.actions] == [("left", "stray")]
    assert _snapshot(root) == after


def test_dry_run_changes_nothing(archive: Archive, settings: Settings, tmp_path: Path) -> None:
    _temp_left_in_process(settings, _frame_file(tmp_path))
    _orphan(archive)
    report = _verify(archive)
    before = _snapshot(settings.archive)

    planned = archive.repair(report, dry_run=True, min_age=NOW)

    assert _snapshot(settings.archive) == before
    assert not (settings.archive / "quarantine").exists()
    assert sorted(a.action for a in planned.actions) == ["deleted", "quarantined"]
    assert [a.verb(True) for a in planned.actions if a.action == "deleted"] == ["would delete"]
    assert not planned.ok  # nothing was changed, so the problems are still there
    assert planned.summary().startswith("dry run, nothing changed: would delete 1")
    # the dry run told the truth: the real run does just that
    real = archive.repair(report, min_age=NOW)
    assert [a.action for a in real.actions] == [a.action for a in planned.actions]
    assert real.ok


def test_young_leftovers_are_left_for_a_later_run(
    archive: Archive, settings: Settings, tmp_path: Path
) -> None:
    """A fresh temp or orphan may be an ingest still at work: no lock can tell, age can."""
    _temp_left_in_process(settings, _frame_file(tmp_path))
    _orphan(archive)
    before = _snapshot(settings.archive)

    done = archive.repair(_verify(archive))  # default min_age: one hour

    assert [a.action for a in done.actions] == ["deferred", "deferred"]
    assert all("run again later" in a.detail for a in done.actions)
    assert _snapshot(settings.archive) == before


def test_an_orphan_that_gets_its_row_after_verify_is_not_moved(
    archive: Archive, settings: Settings, tmp_path: Path
) -> None:
    """The race: verify sees an ingest between publishing its file and committing its row."""
    signal = str(tmp_path / "ingest")
    ingest = _start_ingest(settings, _frame_file(tmp_path), "renamed", pause=signal)
    try:
        deadline = time.monotonic() + 120
        while not Path(signal + ".reached").exists():
            assert ingest.poll() is None, ingest.communicate()[1]
            assert time.monotonic() < deadline
            time.sleep(0.05)
        report = _verify(archive)
        (orphan,) = report.problems
        assert orphan.kind == "orphaned" and orphan.path is not None
        content = _sha(orphan.path)
        Path(signal + ".go").touch()  # the ingest commits its row now
        _out, err = ingest.communicate(timeout=120)
        assert ingest.returncode == 0, err
    finally:
        if ingest.poll() is None:
            ingest.kill()
            ingest.wait()

    done = archive.repair(report, min_age=NOW)

    assert [a.action for a in done.actions] == ["resolved"]
    assert "committed since verify ran" in done.actions[0].detail
    assert _sha(orphan.path) == content
    assert not (settings.archive / "quarantine").exists()
    assert _verify(archive).problems == []


def test_a_row_committed_during_the_move_gets_its_file_back(
    archive: Archive, settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On PostgreSQL the write lock excludes nothing, so repair looks again after the move."""
    uid = _orphan(archive)
    path = archive.raw.path_for(uid)
    content = _sha(path)
    (stored,) = archive.raw.frames(uid)
    report = _verify(archive)
    real_move = repair_module._move
    moves: list[tuple[Path, Path]] = []

    def move_then_commit(source: Path, destination: Path) -> None:
        real_move(source, destination)
        moves.append((source, destination))
        if len(moves) == 1:  # a writer that does not take the lock commits the row now
            with archive.session() as s:
                s.add(Acquisition(
                    uid=uid, kind="test", acquired_at=dt.datetime.now(dt.UTC),
                    frames=[Frame(index=0, role="raster", height=32, width=40, dtype="uint8",
                                  sha256=stored.sha256, store_path=stored.path,
                                  dataset=stored.dataset)],
                ))

    monkeypatch.setattr(repair_module, "_move", move_then_commit)
    done = archive.repair(report, min_age=NOW)

    assert [a.action for a in done.actions] == ["resolved"]
    assert "put back" in done.actions[0].detail
    assert len(moves) == 2 and moves[1] == (moves[0][1], path)
    assert _sha(path) == content
    assert done.quarantine is None
    assert not list((settings.archive / "quarantine").rglob(MANIFEST))
    assert _verify(archive).problems == []


def test_the_check_and_move_happen_under_the_write_lock(
    archive: Archive, monkeypatch: pytest.MonkeyPatch
) -> None:
    _orphan(archive)
    held: list[bool] = []
    real_lock = archive.write_lock

    @contextmanager
    def spying_lock() -> Iterator[None]:
        with real_lock():
            held.append(True)
            try:
                yield
            finally:
                held.pop()

    checks: list[bool] = []
    real_check, real_move = repair_module._has_row, repair_module._move
    monkeypatch.setattr(archive, "write_lock", spying_lock)
    monkeypatch.setattr(repair_module, "_has_row",
                        lambda *a: checks.append(bool(held)) or real_check(*a))
    monkeypatch.setattr(repair_module, "_move",
                        lambda *a: checks.append(bool(held)) or real_move(*a))

    done = archive.repair(_verify(archive), min_age=NOW)

    assert [a.action for a in done.actions] == ["quarantined"]
    assert checks == [True, True, True]  # look, move, look again: all inside the lock


def test_missing_and_corrupt_raw_frames_are_never_touched(
    archive: Archive, settings: Settings, tmp_path: Path
) -> None:
    gone = archive.ingest([FrameSource(_frame_file(tmp_path, 1))], patient="P001")
    damaged = archive.ingest([FrameSource(_frame_file(tmp_path, 2))], patient="P001")
    archive.raw.path_for(gone.uid).unlink()
    path = archive.raw.path_for(damaged.uid)
    with h5py.File(path, "r") as h5:
        offset = h5["frames/0"].id.get_offset()
    with path.open("r+b") as fh:
        fh.seek(offset)
        byte = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([byte[0] ^ 1]))
    before = _snapshot(settings.archive)

    done = archive.repair(_verify(archive), min_age=NOW)

    # the damaged frame differs from its own hash and from the catalogue's: two problems
    assert {(a.kind, a.action) for a in done.actions} == {
        ("corrupt", "attention"), ("missing", "attention")}
    assert all("from backup" in a.detail for a in done.actions)
    assert _snapshot(settings.archive) == before
    assert not done.ok and f"{len(done.actions)} need(s) a person" in done.summary()


def test_only_files_named_as_the_stores_name_them_are_acted_on(
    archive: Archive, settings: Settings
) -> None:
    """A report naming another file (the catalogue, say) must not make repair delete it."""
    uid = uuid.uuid4().hex
    settings.archive.mkdir(parents=True, exist_ok=True)
    outside = settings.archive / "catalog-copy.sqlite"
    outside.write_bytes(b"precious")
    wrong_shard = settings.archive / "raw" / "00" / "00" / f"{uid}.h5.tmp-1-00000000"
    wrong_shard.parent.mkdir(parents=True)
    wrong_shard.write_bytes(b"not where its uid belongs")
    report = VerifyReport(problems=[
        Problem("temporary", uid, outside, "made up"),
        Problem("orphaned", uid, wrong_shard, "made up"),
        Problem("temporary", None, None, "made up"),
    ])

    done = archive.repair(report, min_age=NOW)

    assert [a.action for a in done.actions] == ["left", "left", "left"]
    assert outside.read_bytes() == b"precious" and wrong_shard.exists()


def test_one_repair_at_a_time(archive: Archive, settings: Settings, tmp_path: Path) -> None:
    _temp_left_in_process(settings, _frame_file(tmp_path))
    report = _verify(archive)
    fd = os.open(settings.archive, os.O_RDONLY)  # what a running repair holds
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with pytest.raises(ConflictError, match="running"):
            archive.repair(report, min_age=NOW)
    finally:
        os.close(fd)
    assert archive.repair(report, min_age=NOW).ok


def test_a_quarantined_name_is_never_replaced(archive: Archive, settings: Settings) -> None:
    """The same orphan quarantined twice on one day (restored and orphaned again) keeps both."""
    uid = _orphan(archive)
    path = archive.raw.path_for(uid)
    first = archive.repair(_verify(archive), min_age=NOW)
    assert first.quarantine is not None
    copy = first.quarantine / path.relative_to(settings.archive)
    os.link(copy, path)  # someone puts it back without a row

    second = archive.repair(_verify(archive), min_age=NOW)

    assert second.actions[0].destination is not None
    assert second.actions[0].destination.endswith(f"{uid}~2.h5")
    assert copy.exists() and copy.with_name(f"{uid}~2.h5").exists()
    entries = json.loads((first.quarantine / MANIFEST).read_text())["entries"]
    assert [e["quarantined"].rsplit("/", 1)[1] for e in entries] == [f"{uid}.h5", f"{uid}~2.h5"]


def test_report_of_nothing_is_nothing_to_repair() -> None:
    assert RepairReport().summary() == "repair: nothing to repair"
    assert RepairReport().ok
