"""The backup order of docs/deployment.md, and `rasterserver verify` proving a restore.

An ingest publishes its HDF5 file before it commits the catalogue row, so a catalogue backed
up first names only files that already exist when the files are copied afterwards: the
restore has at most orphaned files (written after the catalogue backup), never a row without
its file. The other order loses files of rows committed in between. Both catalogues: SQLite's
online backup, PostgreSQL's pg_dump / pg_restore into a new database.
"""

from __future__ import annotations

import shutil
import sqlite3
import subprocess
import uuid
from pathlib import Path

import numpy as np
import pytest
from installed_cli import run_installed
from sqlalchemy import text
from sqlalchemy.engine import make_url

from rasterserver.archive import Archive, FrameSource
from rasterserver.catalog.database import make_engine
from rasterserver.config import Settings, sqlite_url


def _ingest(archive: Archive, folder: Path, seed: int) -> str:
    path = folder / f"frame-{seed}.npy"
    np.save(path, np.random.default_rng(seed).integers(0, 4096, (48, 64), dtype=np.uint16))
    return archive.ingest([FrameSource(path)], patient="P-1").uid


def _libpq(url: str) -> str:
    """The SQLAlchemy URL as the libpq URI pg_dump and pg_restore take."""
    return make_url(url).set(drivername="postgresql").render_as_string(hide_password=False)


def _copy_files(archive: Path, target: Path) -> None:
    """The archive's files, without the SQLite catalogue (backed up on its own)."""
    shutil.copytree(archive, target, dirs_exist_ok=True,
                    ignore=shutil.ignore_patterns("catalog.sqlite*"))


class Catalogue:
    """Back up one catalogue and restore it under a new name (the restore's database)."""

    def __init__(self, settings: Settings, work: Path) -> None:
        self.settings, self.work = settings, work
        self.sqlite = settings.database_url.startswith("sqlite")
        self.made: list[str] = []

    def backup(self, name: str) -> Path:
        dump = self.work / name
        if self.sqlite:
            # the online backup API, as `sqlite3 catalog.sqlite ".backup FILE"` uses it
            source = sqlite3.connect(self.settings.archive / "catalog.sqlite")
            target = sqlite3.connect(dump)
            with target:
                source.backup(target)
            source.close()
            target.close()
        else:
            subprocess.run(["pg_dump", "--format=custom", f"--file={dump}",
                            _libpq(self.settings.database_url)], check=True)
        return dump

    def restore(self, dump: Path, archive: Path) -> str:
        if self.sqlite:
            archive.mkdir(parents=True, exist_ok=True)
            shutil.copy2(dump, archive / "catalog.sqlite")
            return sqlite_url(archive)
        name = f"rs_restore_{uuid.uuid4().hex[:12]}"
        admin = make_engine(self.settings.database_url, isolation_level="AUTOCOMMIT")
        with admin.connect() as conn:
            conn.execute(text(f'CREATE DATABASE "{name}"'))
        admin.dispose()
        self.made.append(name)
        url = make_url(self.settings.database_url).set(database=name).render_as_string(
            hide_password=False)
        subprocess.run(["pg_restore", "--no-owner", f"--dbname={_libpq(url)}", str(dump)],
                       check=True)
        return url

    def drop(self) -> None:
        if not self.made:
            return
        admin = make_engine(self.settings.database_url, isolation_level="AUTOCOMMIT")
        with admin.connect() as conn:
            for name in self.made:
                conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@pytest.fixture
def catalogue(settings: Settings, tmp_path: Path) -> Catalogue:
    if not settings.database_url.startswith("sqlite") and not (
        shutil.which("pg_dump") and shutil.which("pg_restore")
    ):
        pytest.skip("pg_dump / pg_restore not installed")
    made = Catalogue(settings, tmp_path)
    yield made
    made.drop()


def test_catalogue_first_then_files_restores_and_verify_proves_it(
    settings: Settings, catalogue: Catalogue, tmp_path: Path
) -> None:
    with Archive.create(settings) as archive:
        archive.add_patient("P-1")
        before = [_ingest(archive, tmp_path, seed) for seed in (1, 2)]
        dump = catalogue.backup("catalogue.backup")  # 1. the catalogue
        during = _ingest(archive, tmp_path, 3)  # an ingest while the backup runs
        _copy_files(settings.archive, tmp_path / "files.backup")  # 2. then the files

    restored = tmp_path / "restored"
    shutil.copytree(tmp_path / "files.backup", restored)
    url = catalogue.restore(dump, restored)

    checked = run_installed("verify", archive=restored, database_url=url)
    assert checked.returncode == 5, checked.stdout + checked.stderr
    problems = [line.split("\t")[:2] for line in checked.stdout.splitlines() if "\t" in line]
    # every row's file is there with its frames' SHA-256; only the later ingest's file is
    # extra, as an orphan
    assert problems == [["orphaned", during]], checked.stdout
    assert "checked 2 acquisitions, 2 frames" in checked.stdout

    repaired = run_installed("verify", "--repair", "--min-age", "0",
                             archive=restored, database_url=url)
    assert repaired.returncode == 0, repaired.stdout + repaired.stderr
    assert list((restored / "quarantine").rglob(f"{during}.h5"))
    final = run_installed("verify", archive=restored, database_url=url)
    assert final.returncode == 0, final.stdout + final.stderr
    assert "checked 2 acquisitions, 2 frames, 0 stored results: OK" in final.stdout
    with Archive(Settings(archive=restored, database_url=url)) as archive:
        assert sorted(a.uid for a in archive.acquisitions(patient="P-1")) == sorted(before)


def test_files_first_then_catalogue_loses_files_verify_says_so(
    settings: Settings, catalogue: Catalogue, tmp_path: Path
) -> None:
    with Archive.create(settings) as archive:
        archive.add_patient("P-1")
        _ingest(archive, tmp_path, 1)
        _copy_files(settings.archive, tmp_path / "files.backup")  # files first ...
        during = _ingest(archive, tmp_path, 2)
        dump = catalogue.backup("catalogue.backup")  # ... then the catalogue

    restored = tmp_path / "restored"
    shutil.copytree(tmp_path / "files.backup", restored)
    url = catalogue.restore(dump, restored)
    with Archive(Settings(archive=restored, database_url=url)) as archive:
        report = archive.verify()
    assert [(p.kind, p.uid) for p in report.problems] == [("missing", during)]
