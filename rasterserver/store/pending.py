"""Files of many results made durable together: two filesystem syncs instead of one per file.

A Dask task stores the results of sixteen acquisitions, seven files each. Synced one by one,
every file and every shard folder costs a journal commit and a wait for the disk: with two
workers, both are often waiting at once and a core idles. Here the files of a whole task are
written under their temporary names without fsync, and then::

    syncfs(area)      # every temporary file's data on stable storage
    publish each      # link to the final name, refusing to replace (:func:`.durable.publish`)
    syncfs(area)      # the names on stable storage

before the task returns, that is before the coordinator commits any row naming them. The
guarantees are those of the per-file recipe in :mod:`.durable`: a final name holds a
complete file or does not exist, a row never names a file that is not on disk, and a crash
leaves at most temporary files (recognisable by their names) and published files without rows
(adopted when the work is redone).

``syncfs`` flushes the whole filesystem the derived area is on (other writers' dirty data
too) and reports the writeback errors that happened since the descriptor it is given was
opened (Linux 5.8 and later): the descriptor is opened before the first file is written.
It is as strong as an fsync of each file only where the filesystem commits what it writes
back: a local journaling filesystem, overlay (it syncs its upper one), NFS (its writeback
ends in COMMIT). On FUSE or SMB mounts it may do less than fsync, which reaches the server.
So only on :data:`SYNCFS_FILESYSTEMS`, Linux 5.8 or later, is :attr:`PendingFiles.deferring`
True; elsewhere the writer fsyncs each file as before.
"""

from __future__ import annotations

import ctypes
import os
import platform
import re
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from types import TracebackType
from typing import Any

from rasterserver.errors import ConflictError
from rasterserver.store.durable import ensure_dir, linux_function, publish

__all__ = ["SYNCFS_FILESYSTEMS", "PendingFiles", "filesystem_type", "syncfs_available"]

#: Filesystem types (as in /proc/self/mountinfo) whose syncfs makes every file durable.
SYNCFS_FILESYSTEMS = frozenset(
    {"ext3", "ext4", "xfs", "btrfs", "f2fs", "overlay", "tmpfs", "nfs", "nfs4"}
)


@cache
def _syncfs() -> Callable[[int], int] | None:
    try:
        major, minor = (int(part) for part in platform.release().split(".")[:2])
    except ValueError:
        return None
    if (major, minor) < (5, 8):  # syncfs reports writeback errors from 5.8 on
        return None
    return linux_function("syncfs", [ctypes.c_int])


def syncfs_available() -> bool:
    """Whether this system can make many files durable with one ``syncfs``."""
    return _syncfs() is not None


def filesystem_type(path: Path, mountinfo: str | None = None) -> str | None:
    """The type of the filesystem ``path`` is on, from ``/proc/self/mountinfo`` (Linux).

    Parameters
    ----------
    path : Path
        An existing path (symbolic links are resolved).
    mountinfo : str, optional
        The table's text (read from ``/proc/self/mountinfo`` when not given).

    Returns
    -------
    str or None
        For instance ``"ext4"`` or ``"nfs4"``; None when there is no such table.
    """
    if mountinfo is None:
        try:
            mountinfo = Path("/proc/self/mountinfo").read_text()
        except OSError:
            return None
    target = os.path.realpath(path)
    found: tuple[int, str | None] = (-1, None)
    for line in mountinfo.splitlines():
        fields, separator, rest = line.partition(" - ")
        parts = fields.split()
        if not separator or len(parts) < 5 or not rest.split():
            continue
        point = re.sub(r"\\([0-7]{3})", lambda m: chr(int(m[1], 8)), parts[4])  # \040: space
        inside = target == point or target.startswith(point.rstrip("/") + "/")
        if inside and len(point) >= found[0]:  # the deepest; of mounts on one point, the last
            found = (len(point), rest.split()[0])
    return found[1]


@dataclass(frozen=True)
class _File:
    owner: str
    temp: Path
    final: Path
    on_conflict: Callable[[], Any]


class PendingFiles:
    """Temporary files waiting to be made durable and published together.

    Use as a context manager; files still pending when it exits (an error before
    :meth:`publish`) are removed.

    Parameters
    ----------
    folder : Path
        A folder on the filesystem the files are written to (created if missing).
    """

    def __init__(self, folder: Path) -> None:
        self._files: list[_File] = []
        self._fd: int | None = None
        if _syncfs() is not None:
            ensure_dir(folder)
            if filesystem_type(folder) in SYNCFS_FILESYSTEMS:
                # opened before any file is written: syncfs reports errors since this open
                self._fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))

    @property
    def deferring(self) -> bool:
        """True when writers should leave their files unsynced and unpublished here."""
        return self._fd is not None

    def add(self, owner: str, temp: Path, final: Path, on_conflict: Callable[[], Any]) -> None:
        """Queue ``temp`` (written, not synced) to be published as ``final``.

        Parameters
        ----------
        owner : str
            Whose file it is (an acquisition uid): :meth:`publish` reports errors by owner.
        temp, final : Path
            Temporary and final name, in the same folder.
        on_conflict : callable
            Called when ``final`` exists already at publication; raises
            :class:`~rasterserver.errors.ConflictError` unless the existing file is this one
            (a redone computation adopts it).
        """
        self._files.append(_File(owner, temp, final, on_conflict))

    def publish(self) -> dict[str, Exception]:
        """Sync, publish and sync again; return the error of each owner that has one.

        Returns
        -------
        dict of str to Exception
            Owners some of whose files could not be made durable or published. A sync that
            fails fails every owner: none of their rows may be committed.
        """
        files, self._files = self._files, []
        errors: dict[str, Exception] = {}
        if not files:
            self.close()
            return errors
        try:
            self._sync()
        except OSError as exc:
            for item in files:
                item.temp.unlink(missing_ok=True)
                errors[item.owner] = exc
            self.close()
            return errors
        for item in files:
            if item.owner in errors:
                item.temp.unlink(missing_ok=True)
                continue
            try:
                publish(item.temp, item.final, sync_dir=False)
            except ConflictError:  # published by another writer, or by this work before
                try:
                    item.on_conflict()
                except Exception as exc:
                    errors[item.owner] = exc
            except OSError as exc:
                item.temp.unlink(missing_ok=True)
                errors[item.owner] = exc
        try:
            self._sync()
        except OSError as exc:
            errors.update({item.owner: exc for item in files})
        finally:
            self.close()
        return errors

    def _sync(self) -> None:
        function = _syncfs()
        assert function is not None and self._fd is not None
        if function(self._fd) != 0:
            code = ctypes.get_errno()
            raise OSError(code, f"syncfs of the derived area failed: {os.strerror(code)}")

    def close(self) -> None:
        """Remove the files still pending and let go of the filesystem."""
        for item in self._files:
            item.temp.unlink(missing_ok=True)
        self._files = []
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> PendingFiles:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
