"""Durable file publication: fsync, and a rename that never replaces an existing file.

Shared by the raw store and the derived-results store. The recipe for a crash-safe
write-once file is::

    ensure_dir(folder)                 # new folders are fsynced into their parents
    ... write folder/<name>.tmp-... ...
    fsync_file(temp)                   # the data reach the disk before the name does
    publish(temp, final)               # atomic, refuses to replace, fsyncs the folder

After a crash, ``final`` either does not exist or is complete; a temp file may be left behind
and is recognisable by its name.
"""

from __future__ import annotations

import ctypes
import errno
import os
import sys
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any

from rasterserver.errors import ConflictError
from rasterserver.store.modes import dir_mode, set_dir_mode, set_file_mode

__all__ = ["ensure_dir", "fsync_dir", "fsync_file", "publish", "start_writeback", "write_synced"]

_SYNC_FILE_RANGE_WRITE = 2  # <linux/fs.h>: start writeback of the range's dirty pages

# Filesystems without hard links (some SMB/FUSE mounts) answer link() with one of these.
_NO_LINK_ERRNOS = frozenset(
    {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS, errno.EMLINK}
)


def fsync_file(path: Path) -> None:
    """Flush a closed file's data to stable storage.

    Parameters
    ----------
    path : Path
        The file.
    """
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_synced(path: Path, data: bytes, *, sync: bool = True) -> None:
    """Create ``path`` (it must not exist), write ``data`` and fsync it, with one open.

    For files built in memory (the derived store's HDF5 images): one ``write`` and one
    ``fsync`` on the descriptor that wrote them, instead of a library's many small writes
    and a second open to fsync.

    Parameters
    ----------
    path : Path
        New file (a temporary name; :func:`publish` gives it its final one).
    data : bytes
        The whole contents.
    sync : bool, optional
        False leaves the fsync to the caller, who syncs the whole filesystem once for many
        files before publishing any of them (:class:`.pending.PendingFiles`); the data's
        writeback is started here (:func:`start_writeback`) so that the sync finds little
        left to wait for.

    Raises
    ------
    FileExistsError
        ``path`` exists.
    """
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        view = memoryview(data)
        while view:
            written = os.write(fd, view)
            view = view[written:]
        if sync:
            os.fsync(fd)
        else:
            start_writeback(fd)
    finally:
        os.close(fd)


def linux_function(name: str, argtypes: list[Any]) -> Callable[..., int] | None:
    """The C library's function ``name`` (returning int) on Linux; None elsewhere or if absent.

    Parameters
    ----------
    name : str
        For instance ``"syncfs"``.
    argtypes : list
        Its parameters' ctypes types.
    """
    if sys.platform != "linux":
        return None
    try:
        function = getattr(ctypes.CDLL(None, use_errno=True), name)
    except (OSError, AttributeError):
        return None
    function.argtypes = argtypes
    function.restype = ctypes.c_int
    return function


@cache
def _sync_file_range() -> Callable[..., int] | None:
    return linux_function(
        "sync_file_range", [ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint]
    )


def start_writeback(fd: int) -> None:
    """Start writing an open file's dirty pages to disk, without waiting (Linux; else nothing).

    Only a hint: it makes nothing durable (the metadata are not written, errors are not
    reported). A later fsync or syncfs of many files then waits for little more than the
    journal: measured with 16 acquisitions' files written between 35 ms of computing each,
    the syncfs of them took 37 ms without this, 1.2 ms with it.

    Parameters
    ----------
    fd : int
        A descriptor open for writing.
    """
    function = _sync_file_range()
    if function is not None:
        function(fd, 0, 0, _SYNC_FILE_RANGE_WRITE)


def fsync_dir(path: Path) -> None:
    """Flush a folder's entries (file creations, renames) to stable storage.

    Parameters
    ----------
    path : Path
        The folder.
    """
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    except OSError as exc:
        # Some network filesystems refuse fsync on a directory; their rename is durable on
        # return, so there is nothing more to do.
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(fd)


def ensure_dir(path: Path, *, sync: bool = True) -> None:
    """Create ``path`` and missing parents, fsyncing each new entry into its parent.

    Folders created here get the archive's mode (owner only, see
    :mod:`rasterserver.store.modes`); folders that exist already are left as they are.

    Parameters
    ----------
    path : Path
        Folder to create if it does not exist.
    sync : bool, optional
        False leaves the new entries to a sync of the whole filesystem by the caller.
    """
    missing: list[Path] = []
    probe = path
    while not probe.exists():
        missing.append(probe)
        probe = probe.parent
    for folder in reversed(missing):
        try:
            folder.mkdir(mode=dir_mode())
        except FileExistsError:  # another writer created it meanwhile
            continue
        set_dir_mode(folder)  # exactly: the umask may have taken the group's bits
        if sync:
            fsync_dir(folder.parent)


def publish(temp: Path, final: Path, *, sync_dir: bool = True) -> None:
    """Give the complete file ``temp`` its final name, refusing to replace an existing file.

    ``link()`` + ``unlink()`` is used because ``rename()`` silently replaces its target: two
    writers racing for the same name would both "succeed". On filesystems without hard links
    it falls back to check-then-rename, which is not atomic against a concurrent writer.

    Parameters
    ----------
    temp : Path
        Fully written and fsynced file, in the same folder as ``final``.
    final : Path
        Name to publish it under.
    sync_dir : bool, optional
        Fsync the folder (the new name) here. A caller that publishes several files into one
        folder may pass False and call :func:`fsync_dir` once after the last, before anything
        refers to them (the derived store's batches).

    The file gets the archive's mode (owner only, see :mod:`rasterserver.store.modes`)
    before it gets its name, so it is never readable by others under that name.

    Raises
    ------
    ConflictError
        ``final`` already exists; ``temp`` is removed.
    """
    # h5py and open() create files with 0666 less the umask: usually world-readable
    set_file_mode(temp)
    try:
        os.link(temp, final)
    except FileExistsError:
        temp.unlink(missing_ok=True)
        raise ConflictError(f"{final.name} already exists; archive files are write-once") from None
    except OSError as exc:
        if exc.errno not in _NO_LINK_ERRNOS:
            raise
        if final.exists():
            temp.unlink(missing_ok=True)
            raise ConflictError(
                f"{final.name} already exists; archive files are write-once"
            ) from None
        os.rename(temp, final)
    else:
        temp.unlink()
    if sync_dir:
        fsync_dir(final.parent)
