"""File modes of what the archive creates: owner-only by default.

The archive holds patient data (raw camera frames, backs, the SQLite catalogue), so every
folder it creates is ``0700`` and every file ``0600``, whatever the process's umask: a umask
can only take permissions away, and the usual ``022`` would leave everything readable by
every account on the machine. The modes are set explicitly at creation (``mkdir``/``open``
with the mode, then ``chmod``), never by changing the process's umask, which would touch
every other file the process writes (exports, reports chosen by the user).

``RASTERSERVER_GROUP_ACCESS=1`` gives the owner's group read access (files ``0640``, folders
``0750``), for a site where a second service account (a backup agent, a read-only worker)
shares a group with the server's account. Write access is never given to the group: the
archive is write-once and only rasterserver writes it.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["GROUP_ACCESS_ENV", "dir_mode", "file_mode", "make_private_file", "set_dir_mode",
           "set_file_mode"]

#: Environment variable that opens the archive to the owner's group (read only).
GROUP_ACCESS_ENV = "RASTERSERVER_GROUP_ACCESS"


def _group_access() -> bool:
    return os.environ.get(GROUP_ACCESS_ENV, "").strip().lower() in ("1", "true", "yes", "on")


def file_mode() -> int:
    """Mode of the archive's files: ``0o600``, or ``0o640`` with group access."""
    return 0o640 if _group_access() else 0o600


def dir_mode() -> int:
    """Mode of the archive's folders: ``0o700``, or ``0o750`` with group access."""
    return 0o750 if _group_access() else 0o700


def set_file_mode(path: Path) -> None:
    """Give the archive's file ``path`` its mode (see :func:`file_mode`)."""
    os.chmod(path, file_mode())


def set_dir_mode(path: Path) -> None:
    """Give the archive's folder ``path`` its mode (see :func:`dir_mode`)."""
    os.chmod(path, dir_mode())


def make_private_file(path: Path) -> bool:
    """Create the empty file ``path`` with the archive's file mode, unless it exists.

    Returns
    -------
    bool
        True if this call created it.
    """
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, file_mode())
    except FileExistsError:
        return False
    try:
        os.fchmod(fd, file_mode())  # the umask may have taken bits of the group option
    finally:
        os.close(fd)
    return True
