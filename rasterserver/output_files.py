"""Files written for the user (exports, point clouds, calibration JSON, reports, images).

An output path comes from the command line, so it may name a folder, a folder that does not
exist, a read-only place or a device. :func:`check_output` refuses such a path with a sentence
*before* the work that produces the file starts (a calibration takes seconds, a simulation
longer), and :func:`output_file` writes the file under a temporary name beside it and renames
it over the target only once it is complete: an interrupted or failed write leaves the old
file (or none), never half a file.

Errors are :class:`~rasterserver.errors.InputError` (exit 2): the path given cannot be
written, whatever the reason the operating system gives.
"""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from rasterserver.errors import InputError
from rasterserver.store.durable import fsync_dir, fsync_file

__all__ = ["check_output", "check_output_folder", "output_file"]

#: Temporary files are hidden and say what they are, should a crash leave one behind.
_TEMP_MARK = ".tmp-"


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def _probe(folder: Path, shown: Path) -> None:
    """Create and remove a file in ``folder``: the only sure test that it can be written to
    (permission bits say nothing for root, a read-only mount or a full disk)."""
    probe = folder / f".{secrets.token_hex(6)}{_TEMP_MARK}probe"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise InputError(f"cannot write {shown}: {_reason(exc)}") from None
    os.close(fd)
    probe.unlink(missing_ok=True)


def check_output(path: Path | str, *, what: str = "output file") -> Path:
    """Refuse an output file that cannot be written, before anything is computed.

    Parameters
    ----------
    path : Path or str
        The file to (over)write.
    what : str, optional
        What the file is, for messages (``"--out"``, ``"report"``).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    InputError
        ``path`` is a folder or another non-regular file (a device, a pipe), its folder does
        not exist or is not a folder, or nothing can be created in that folder.
    """
    path = Path(path)
    if not path.name or path.name in (".", ".."):
        raise InputError(f"{what} {path}: name a file, not a folder")
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise InputError(f"{what} {path}: cannot be written ({_reason(exc)})") from None
    if mode is not None and stat.S_ISDIR(mode):
        raise InputError(f"{what} {path}: is a folder; name a file in it")
    if mode is not None and not stat.S_ISREG(mode):
        raise InputError(f"{what} {path}: exists and is not a regular file")
    folder = path.parent
    if not folder.exists():
        raise InputError(f"{what} {path}: folder {folder} does not exist")
    if not folder.is_dir():
        raise InputError(f"{what} {path}: {folder} is not a folder")
    _probe(folder, path)
    return path


def check_output_folder(path: Path | str, *, what: str = "output folder") -> Path:
    """Refuse an output folder that cannot be made or written, before anything is computed.

    A folder that does not exist yet is fine when it can be created: the nearest existing
    ancestor must be a folder that can be written to.

    Parameters
    ----------
    path : Path or str
        The folder to write files into (created by the writer if missing).
    what : str, optional
        What the folder is, for messages.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    InputError
        ``path`` or an ancestor is a file, or nothing can be created where it is.
    """
    path = Path(path)
    probe = path
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        if probe == path:
            raise InputError(f"{what} {path}: exists and is not a folder")
        raise InputError(f"{what} {path}: {probe} is a file, not a folder")
    _probe(probe if probe.exists() else Path.cwd(), path)
    return path


@contextmanager
def output_file(path: Path | str, *, what: str = "output file") -> Iterator[Path]:
    """Yield a temporary path to write to; on success it replaces ``path`` in one rename.

    The temporary file lies in ``path``'s folder (a rename does not cross filesystems) and
    keeps ``path``'s suffix, as writers that choose the format by the suffix need. It is
    fsynced before the rename; on any error it is removed and ``path`` is left as it was.

    Parameters
    ----------
    path : Path or str
        The file to (over)write; checked with :func:`check_output` first.
    what : str, optional
        What the file is, for messages.

    Yields
    ------
    Path
        Where the caller writes the complete file.

    Raises
    ------
    InputError
        ``path`` cannot be written (see :func:`check_output`), or writing failed (a full
        disk, say): the operating system's reason is given.
    """
    path = check_output(path, what=what)
    temp = path.with_name(f".{path.name}{_TEMP_MARK}{secrets.token_hex(4)}{path.suffix}")
    try:
        yield temp
        if not temp.is_file():
            raise InputError(f"{what} {path}: nothing was written")
        fsync_file(temp)
        os.replace(temp, path)
        fsync_dir(path.parent)
    except OSError as exc:
        raise InputError(f"cannot write {path}: {_reason(exc)}") from None
    finally:
        temp.unlink(missing_ok=True)
