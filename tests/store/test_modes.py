"""Owner-only modes of everything the archive creates (rasterserver.store.modes), read back
with os.stat: the SQLite catalogue, its WAL and shared-memory files, raw and derived HDF5
files and their folders, the lock file and the pseudonym key file; the group option; a
permissive umask changes nothing. On PostgreSQL the archive folder holds no catalogue, and
the files it does hold get the same modes."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from rasterserver.archive import Archive, FrameSource
from rasterserver.config import Settings
from rasterserver.records_surface import Surface
from rasterserver.services.pseudonyms import Pseudonymiser
from rasterserver.store.derived import DerivedStore
from rasterserver.store.modes import GROUP_ACCESS_ENV

KEY = "ab" * 32


@pytest.fixture
def permissive_umask() -> Iterator[None]:
    """The umask of a careless service unit: new files would be world-writable."""
    old = os.umask(0)
    try:
        yield
    finally:
        os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _fill(settings: Settings) -> tuple[Archive, list[Path]]:
    """An archive with a patient, one acquisition, a derived result and a pseudonym key."""
    archive = Archive.create(settings)
    archive.add_patient("P-1")
    frame = np.arange(604 * 576, dtype=np.uint16).reshape(604, 576) % 4000
    acq = archive.ingest([FrameSource(frame, role="raster", name="f")], patient="P-1",
                         kind="patient")
    raw = archive.raw.path_for(acq.uid)
    derived = DerivedStore(settings.archive).write(
        acq.uid, Surface(x0=0.0, y0=0.0, spacing=1.0, z=np.ones((2, 2))), stage="surface",
        plugin="x", plugin_version="1", params={}, params_hash="ab" * 32,
        chain_key="cd" * 32, input_checksum="ef" * 32)
    Pseudonymiser(archive).pseudonym("P-1")  # makes the key file
    return archive, [raw, settings.archive / derived.path]


def _archive_entries(root: Path) -> tuple[list[Path], list[Path]]:
    files, folders = [], [root]
    for path in root.rglob("*"):
        (folders if path.is_dir() else files).append(path)
    return files, folders


def test_the_archive_is_owner_only(settings: Settings, permissive_umask, monkeypatch) -> None:
    monkeypatch.delenv(GROUP_ACCESS_ENV, raising=False)
    monkeypatch.delenv("RASTERSERVER_PSEUDONYM_KEY", raising=False)
    monkeypatch.delenv("RASTERSERVER_PSEUDONYM_KEY_FILE", raising=False)
    archive, written = _fill(settings)
    try:
        files, folders = _archive_entries(settings.archive)
        names = {p.name for p in files}
        if settings.database_url.startswith("sqlite"):
            # the catalogue and, while it is open, its WAL and shared memory
            assert {"catalog.sqlite", "catalog.sqlite-wal", "catalog.sqlite-shm"} <= names
        assert "pseudonym.key" in names and all(p in files for p in written)
        assert len(folders) >= 7  # root, raw/aa/bb, derived/aa/bb, config
        assert {str(p): oct(_mode(p)) for p in files if _mode(p) != 0o600} == {}
        assert {str(p): oct(_mode(p)) for p in folders if _mode(p) != 0o700} == {}
    finally:
        archive.close()


def test_group_access_gives_the_group_read_only(tmp_path: Path, permissive_umask,
                                                monkeypatch) -> None:
    from rasterserver.config import sqlite_url

    monkeypatch.setenv(GROUP_ACCESS_ENV, "1")
    monkeypatch.setenv("RASTERSERVER_PSEUDONYM_KEY", KEY)
    root = tmp_path / "archive"
    archive, written = _fill(Settings(archive=root, database_url=sqlite_url(root)))
    try:
        files, folders = _archive_entries(root)
        assert {str(p): oct(_mode(p)) for p in files
                if _mode(p) != 0o640 and p.suffix != ".lock"} == {}
        assert {str(p): oct(_mode(p)) for p in folders if _mode(p) != 0o750} == {}
        assert all(_mode(p) == 0o640 for p in written)
    finally:
        archive.close()


def test_existing_folders_are_left_alone(tmp_path: Path, permissive_umask, monkeypatch) -> None:
    from rasterserver.config import sqlite_url

    monkeypatch.delenv(GROUP_ACCESS_ENV, raising=False)
    monkeypatch.setenv("RASTERSERVER_PSEUDONYM_KEY", KEY)
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o755)
    shared.chmod(0o755)
    root = shared / "archive"
    Archive.create(Settings(archive=root, database_url=sqlite_url(root))).close()
    assert _mode(shared) == 0o755 and _mode(root) == 0o700
    assert _mode(root / "catalog.sqlite") == 0o600
