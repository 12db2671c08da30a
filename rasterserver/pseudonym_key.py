"""Where the researchers' pseudonym key lives: outside the catalogue.

The key turns site identifiers into pseudonyms and sets every patient's date shift
(:mod:`rasterserver.services.pseudonyms`). Whoever holds it with a copy of the research data can
re-identify the patients, so it must not travel with the catalogue: a database dump or
backup handed to someone must not carry it. It is read, in this order, from

``RASTERSERVER_PSEUDONYM_KEY``
    The key as hex (at least 16 bytes), e.g. from the service manager's secret store.
``RASTERSERVER_PSEUDONYM_KEY_FILE``
    A file holding the key as hex, mode 0600 (refused when others may read it). Default:
    ``<archive>/config/pseudonym.key``. A clinic should put it outside the archive and
    outside the catalogue's backups (e.g. ``/etc/rasterserver/pseudonym.key``) and back it
    up on its own.

Without either, a new key is made in the key file on first use. Migration 0010 moved the key
that earlier versions kept in the catalogue (table ``pseudonym_key``) into that file.
:func:`rotate_key` replaces it (``rasterserver keys rotate-pseudonyms``): every pseudonym
and date shift changes.
"""

from __future__ import annotations

import logging
import os
import secrets
import stat
from pathlib import Path

from rasterserver.config import Settings
from rasterserver.errors import ConflictError, InputError
from rasterserver.store.durable import ensure_dir, fsync_dir, fsync_file, publish
from rasterserver.store.layout import temp_path

__all__ = ["KEY_ENV", "KEY_FILE_ENV", "key_file", "load_key", "parse_key", "read_key_file",
           "rotate_key", "write_key_file"]

log = logging.getLogger(__name__)

KEY_ENV = "RASTERSERVER_PSEUDONYM_KEY"
KEY_FILE_ENV = "RASTERSERVER_PSEUDONYM_KEY_FILE"
MIN_KEY_BYTES = 16


def key_file(settings: Settings) -> Path:
    """The key file of the archive ``settings`` describes (see the module's text)."""
    configured = os.environ.get(KEY_FILE_ENV, "").strip()
    if configured:
        return Path(configured).expanduser().resolve()
    return settings.archive / "config" / "pseudonym.key"


def parse_key(text: str, source: str) -> bytes:
    """The key written as hex in ``text``; ``source`` names where it came from for errors.

    Raises
    ------
    InputError
        Not hex, or shorter than 16 bytes.
    """
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise InputError(f"{source} must hold the pseudonym key as hex digits") from None
    if len(key) < MIN_KEY_BYTES:
        raise InputError(f"{source} must hold at least {MIN_KEY_BYTES} bytes "
                         f"({2 * MIN_KEY_BYTES} hex digits)")
    return key


def read_key_file(path: Path) -> bytes | None:
    """The key in ``path``, or None when there is no such file.

    Raises
    ------
    InputError
        Others than the owner (and, with group access, the group) may read or write the
        file, it is not a regular file, or it does not hold a key.
    """
    try:
        info = path.stat()
    except FileNotFoundError:
        return None
    if not stat.S_ISREG(info.st_mode):
        raise InputError(f"the pseudonym key file {path} is not a regular file")
    if info.st_mode & 0o027:
        # like ssh with a private key: a key others can read is no secret
        raise InputError(f"the pseudonym key file {path} may be read or written by others "
                         f"(mode {stat.S_IMODE(info.st_mode):o}): `chmod 600 {path}`")
    return parse_key(path.read_text(encoding="ascii", errors="replace"),
                     f"the pseudonym key file {path}")


def write_key_file(path: Path, key: bytes, *, replace: bool = False) -> None:
    """Write ``key`` to ``path`` as hex, mode 0600, whole or not at all.

    Parameters
    ----------
    path : Path
        The key file; missing folders are made owner-only.
    key : bytes
        The key.
    replace : bool
        Replace an existing file (rotation); otherwise an existing file is a conflict.

    Raises
    ------
    ConflictError
        ``path`` exists and ``replace`` is false.
    """
    ensure_dir(path.parent)
    temp = temp_path(path)
    fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.write(fd, (key.hex() + "\n").encode("ascii"))
        os.fchmod(fd, 0o600)  # never the group: the key re-identifies research data
    finally:
        os.close(fd)
    fsync_file(temp)
    if replace:
        os.replace(temp, path)
        fsync_dir(path.parent)
    else:
        publish(temp, path)  # refuses to replace; gives the archive's file mode
        os.chmod(path, 0o600)


def load_key(settings: Settings, *, create: bool = True) -> bytes:
    """The pseudonym key: from ``RASTERSERVER_PSEUDONYM_KEY``, else the key file.

    Parameters
    ----------
    settings : Settings
        The archive (for the default key file).
    create : bool
        Make a new key in the key file when there is none.

    Raises
    ------
    InputError
        A malformed key, a key file others may read, or no key and ``create`` false.
    """
    env = os.environ.get(KEY_ENV, "")
    if env:
        return parse_key(env, KEY_ENV)
    path = key_file(settings)
    key = read_key_file(path)
    if key is not None:
        return key
    if not create:
        raise InputError(f"no pseudonym key: neither {KEY_ENV} nor the key file {path}")
    try:
        write_key_file(path, secrets.token_bytes(32))
        # said loudly: if researchers already hold pseudonyms of this archive, the old key
        # file should have been restored instead (they cannot be linked to the new ones)
        log.warning("no pseudonym key was found: a new one was made in %s", path)
    except ConflictError:
        pass  # another process made it a moment ago: theirs is the key
    key = read_key_file(path)
    assert key is not None
    return key


def rotate_key(settings: Settings, *, keep_old: Path | None = None) -> Path:
    """Replace the key in the key file by a new random key; return the key file.

    Parameters
    ----------
    settings : Settings
        The archive.
    keep_old : Path, optional
        Where to keep the old key (mode 0600, must not exist). Without it the old key is
        gone for good: pseudonyms issued under it can no longer be mapped back, by anyone.

    Raises
    ------
    InputError
        The key comes from ``RASTERSERVER_PSEUDONYM_KEY`` (set a new value there instead).
    ConflictError
        ``keep_old`` exists.
    """
    if os.environ.get(KEY_ENV):
        raise InputError(f"the pseudonym key comes from {KEY_ENV}: rotate it by setting a new "
                         "value there (e.g. `openssl rand -hex 32`)")
    path = key_file(settings)
    old = read_key_file(path)
    if keep_old is not None and old is not None:
        write_key_file(keep_old, old)
    write_key_file(path, secrets.token_bytes(32), replace=True)
    return path
