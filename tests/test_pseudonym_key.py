"""The pseudonym key outside the catalogue (rasterserver.pseudonym_key): where it is read
from, made once with mode 0600, refused when others may read it, rotated."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

from rasterserver.config import Settings, sqlite_url
from rasterserver.errors import ConflictError, InputError
from rasterserver.pseudonym_key import (
    KEY_ENV,
    KEY_FILE_ENV,
    key_file,
    load_key,
    read_key_file,
    rotate_key,
    write_key_file,
)


@pytest.fixture
def settings(tmp_path: Path, monkeypatch) -> Settings:
    monkeypatch.delenv(KEY_ENV, raising=False)
    monkeypatch.delenv(KEY_FILE_ENV, raising=False)
    root = tmp_path / "archive"
    return Settings(archive=root, database_url=sqlite_url(root))


def test_made_once_owner_only_and_stable(settings: Settings) -> None:
    path = key_file(settings)
    assert path == settings.archive / "config" / "pseudonym.key" and not path.exists()
    keys = []
    threads = [threading.Thread(target=lambda: keys.append(load_key(settings)))
               for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(keys)) == 1 and len(keys[0]) == 32  # racing first uses agree
    assert os.stat(path).st_mode & 0o777 == 0o600
    assert load_key(settings) == keys[0] == bytes.fromhex(path.read_text())
    assert [p.name for p in path.parent.iterdir()] == ["pseudonym.key"]  # no temp left


def test_environment_and_configured_file(settings: Settings, tmp_path: Path,
                                         monkeypatch) -> None:
    elsewhere = tmp_path / "etc" / "rs.key"
    monkeypatch.setenv(KEY_FILE_ENV, str(elsewhere))
    assert key_file(settings) == elsewhere
    made = load_key(settings)
    assert read_key_file(elsewhere) == made
    assert not (settings.archive / "config").exists()
    monkeypatch.setenv(KEY_ENV, "cd" * 16)
    assert load_key(settings) == bytes.fromhex("cd" * 16)
    for bad in ("zz", "ab" * 8 + "a", "ab" * 15):
        monkeypatch.setenv(KEY_ENV, bad)
        with pytest.raises(InputError, match=KEY_ENV):
            load_key(settings)


def test_a_key_file_others_may_read_is_refused(settings: Settings) -> None:
    path = key_file(settings)
    write_key_file(path, b"k" * 32)
    with pytest.raises(ConflictError):
        write_key_file(path, b"j" * 32)  # never replaced by accident
    path.chmod(0o644)
    with pytest.raises(InputError, match="chmod 600"):
        load_key(settings)
    path.chmod(0o640)  # the group may read (a service group), no one else
    assert load_key(settings) == b"k" * 32
    path.chmod(0o600)
    path.write_text("not hex\n")
    with pytest.raises(InputError, match="hex"):
        load_key(settings)
    path.unlink()
    with pytest.raises(InputError, match="no pseudonym key"):
        load_key(settings, create=False)


def test_rotation(settings: Settings, tmp_path: Path, monkeypatch) -> None:
    old = load_key(settings)
    kept = tmp_path / "old.key"
    path = rotate_key(settings, keep_old=kept)
    new = load_key(settings)
    assert new != old and read_key_file(kept) == old
    assert os.stat(path).st_mode & 0o777 == 0o600 and os.stat(kept).st_mode & 0o777 == 0o600
    with pytest.raises(ConflictError):
        rotate_key(settings, keep_old=kept)  # an old key is never overwritten
    assert load_key(settings) == new
    rotate_key(settings)
    assert load_key(settings) not in (old, new)
    monkeypatch.setenv(KEY_ENV, "ab" * 16)
    with pytest.raises(InputError, match=KEY_ENV):
        rotate_key(settings)
