"""Files of many results made durable together: nothing named before the sync, adoption of
a file published meanwhile, a conflict reported for its owner alone, nothing left behind."""

from __future__ import annotations

import ctypes
import errno
import hashlib
from pathlib import Path

import numpy as np
import pytest

from rasterserver.errors import ConflictError
from rasterserver.records_surface import Points
from rasterserver.store import pending as pending_module
from rasterserver.store.derived import AREA, DerivedStore
from rasterserver.store.pending import (
    SYNCFS_FILESYSTEMS,
    PendingFiles,
    filesystem_type,
    syncfs_available,
)

UIDS = ("0123456789abcdef0123456789abcdef", "fedcba9876543210fedcba9876543210")
KEY = hashlib.sha256(b"chain").hexdigest()


def _points(seed: int) -> Points:
    rng = np.random.default_rng(seed)
    n = 40
    return Points(
        x=rng.normal(size=n), y=rng.normal(size=n), z=rng.normal(size=n),
        number=np.arange(n, dtype=np.int32), col=np.arange(n, dtype=np.int32),
        row=rng.uniform(0, 600, n), area=rng.uniform(0, 200, n).astype(np.float32),
        image_shape=np.array([604, 576]),
    )


def _write(store: DerivedStore, uid: str, record: Points, pending: PendingFiles | None = None):
    return store.write(
        uid, record, stage="points", plugin="points.ray-plane", plugin_version="1",
        params={}, params_hash="ab" * 32, chain_key=KEY, input_checksum="cd" * 32,
        sync_dir=False, pending=pending,
    )


def _files(store: DerivedStore) -> dict[str, list[Path]]:
    found: dict[str, list[Path]] = {"final": [], "temp": [], "stray": []}
    for entry in store.scan():
        found[entry.kind].append(entry.path)
    return found


def test_this_machine_defers(tmp_path: Path) -> None:
    # the benchmarks and the Docker image run on Linux >= 5.8: the batched path is the one used
    assert syncfs_available()
    assert filesystem_type(tmp_path) in SYNCFS_FILESYSTEMS


MOUNTINFO = r"""22 1 252:0 / / rw,relatime shared:1 - ext4 /dev/vda rw
30 22 0:40 / /mnt/nas rw shared:2 - nfs4 nas:/export rw,vers=4.2
31 22 0:41 / /mnt/my\040share rw shared:3 - cifs //server/share rw
32 30 0:42 / /mnt/nas/cloud rw shared:4 - fuse.sshfs user@host: rw
33 22 0:43 / /mnt/twice rw shared:5 - tmpfs tmpfs rw
34 22 0:44 / /mnt/twice rw shared:6 - cifs //other/share rw
"""


@pytest.mark.parametrize(
    ("path", "expected"),
    [
        ("/srv/archive/derived", "ext4"),
        ("/mnt/nas", "nfs4"),
        ("/mnt/nas/archive/derived", "nfs4"),
        ("/mnt/nasty", "ext4"),  # a prefix of the name is not a mount point above it
        ("/mnt/my share/archive", "cifs"),  # \040 is a space
        ("/mnt/nas/cloud/archive", "fuse.sshfs"),  # the deepest mount point
        ("/mnt/twice/archive", "cifs"),  # of two mounts on one point, the later
    ],
)
def test_the_filesystem_of_a_path(path: str, expected: str) -> None:
    assert filesystem_type(Path(path), MOUNTINFO) == expected


def test_no_mount_table_no_type() -> None:
    assert filesystem_type(Path("/srv"), "") is None


def test_files_get_their_names_only_when_published(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    records = [_points(1), _points(2)]
    with PendingFiles(tmp_path / AREA) as pending:
        assert pending.deferring
        written = [_write(store, uid, r, pending) for uid, r in zip(UIDS, records, strict=True)]
        found = _files(store)
        assert found["final"] == [] and len(found["temp"]) == 2
        assert pending.publish() == {}
    found = _files(store)
    assert found["temp"] == [] and len(found["final"]) == 2
    for result, record in zip(written, records, strict=True):
        assert not result.adopted
        assert store.read(result.path, expected_checksum=record.content_hash()).content_hash() \
            == record.content_hash()


def test_a_file_published_meanwhile_is_adopted(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    record = _points(3)
    with PendingFiles(tmp_path / AREA) as pending:
        _write(store, UIDS[0], record, pending)
        _write(store, UIDS[0], record)  # another worker, same computation, published first
        assert pending.publish() == {}
    found = _files(store)
    assert found["temp"] == [] and len(found["final"]) == 1


def test_a_conflict_fails_its_owner_alone(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    with PendingFiles(tmp_path / AREA) as pending:
        _write(store, UIDS[0], _points(4), pending)
        _write(store, UIDS[1], _points(5), pending)
        _write(store, UIDS[0], _points(6))  # same name, other contents
        errors = pending.publish()
    assert set(errors) == {UIDS[0]} and isinstance(errors[UIDS[0]], ConflictError)
    found = _files(store)
    assert found["temp"] == [] and len(found["final"]) == 2


def test_files_not_published_are_removed(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    with pytest.raises(RuntimeError), PendingFiles(tmp_path / AREA) as pending:
        _write(store, UIDS[0], _points(7), pending)
        raise RuntimeError("the worker gave up before publishing")
    assert _files(store) == {"final": [], "temp": [], "stray": []}
    assert not pending.deferring  # closed: the descriptor is let go


def test_a_failed_sync_fails_every_owner_and_names_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a disk error cannot be made on purpose here: syncfs answers EIO as the kernel would
    def failing(fd: int) -> int:
        ctypes.set_errno(errno.EIO)
        return -1

    store = DerivedStore(tmp_path)
    with PendingFiles(tmp_path / AREA) as pending:
        for uid, seed in zip(UIDS, (8, 9), strict=True):
            _write(store, uid, _points(seed), pending)
        monkeypatch.setattr(pending_module, "_syncfs", lambda: failing)
        errors = pending.publish()
    assert set(errors) == set(UIDS)
    assert all(isinstance(e, OSError) and e.errno == errno.EIO for e in errors.values())
    assert _files(store) == {"final": [], "temp": [], "stray": []}


@pytest.mark.parametrize("where", ["no syncfs", "a FUSE mount"])
def test_without_a_trusted_syncfs_each_file_is_synced_and_published_at_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, where: str
) -> None:
    # a FUSE (or SMB) filesystem's syncfs may not reach the server as each file's fsync does
    if where == "no syncfs":
        monkeypatch.setattr(pending_module, "_syncfs", lambda: None)
    else:
        monkeypatch.setattr(pending_module, "filesystem_type", lambda path: "fuse.sshfs")
    store = DerivedStore(tmp_path)
    with PendingFiles(tmp_path / AREA) as pending:
        assert not pending.deferring
        _write(store, UIDS[0], _points(10), pending)
        assert len(_files(store)["final"]) == 1
        assert pending.publish() == {}
    assert len(_files(store)["final"]) == 1
