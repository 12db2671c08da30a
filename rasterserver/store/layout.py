"""Where archive files live: ``<root>/<area>/<uid[0:2]>/<uid[2:4]>/<uid><suffix>``.

Two levels of 256 shards keep folders small (a million acquisitions is ~15 files per folder)
and let an archive be split across disks by prefix. ``uid`` is 32 lowercase hex digits (a
``uuid4().hex``) chosen by the caller; validating it here also rules out path traversal.

Temporary files are written beside their final name as ``<uid><suffix>.tmp-<pid>-<random>``,
so the shard folder is on the same filesystem (atomic rename) and a leftover is obviously a
partial write of that uid.
"""

from __future__ import annotations

import os
import re
import secrets
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from rasterserver.errors import InputError

__all__ = [
    "ShardEntry",
    "is_uid",
    "scan_area",
    "shard_path",
    "temp_path",
    "validate_uid",
]

_UID = re.compile(r"[0-9a-f]{32}")
_TEMP_MARK = ".tmp-"


def is_uid(text: str) -> bool:
    """Return True if ``text`` is a valid archive uid (32 lowercase hex digits)."""
    return _UID.fullmatch(text) is not None


def validate_uid(uid: str) -> str:
    """Return ``uid`` unchanged if valid.

    Parameters
    ----------
    uid : str
        Candidate uid.

    Returns
    -------
    str
        ``uid``.

    Raises
    ------
    InputError
        ``uid`` is not 32 lowercase hex digits.
    """
    if not isinstance(uid, str) or not is_uid(uid):
        raise InputError(f"invalid archive uid {uid!r}: expected 32 lowercase hex digits")
    return uid


def shard_path(area: Path, uid: str, suffix: str) -> Path:
    """Return the final path of ``uid`` in ``area`` (e.g. ``<root>/raw``).

    Parameters
    ----------
    area : Path
        Top folder of one kind of file.
    uid : str
        Archive uid.
    suffix : str
        File name suffix, with its dot (``".h5"``).

    Returns
    -------
    Path
        ``area/uid[0:2]/uid[2:4]/<uid><suffix>``.
    """
    validate_uid(uid)
    return area / uid[0:2] / uid[2:4] / f"{uid}{suffix}"


def temp_path(final: Path) -> Path:
    """Return a fresh temporary name beside ``final``, unique per process and call.

    Parameters
    ----------
    final : Path
        The name the file will be published under.

    Returns
    -------
    Path
        ``<final>.tmp-<pid>-<8 hex digits>``.
    """
    return final.with_name(f"{final.name}{_TEMP_MARK}{os.getpid()}-{secrets.token_hex(4)}")


@dataclass(frozen=True)
class ShardEntry:
    """One file found in a sharded area.

    Attributes
    ----------
    uid : str or None
        The uid the name stands for; None for a stray file.
    path : Path
        Absolute path of the file.
    kind : {"final", "temp", "stray"}
        ``final``: a published file in its right shard. ``temp``: a leftover partial write
        (a crash, or a writer still running). ``stray``: anything else (unknown name, or a
        uid in the wrong shard).
    """

    uid: str | None
    path: Path
    kind: Literal["final", "temp", "stray"]


def scan_area(area: Path, suffix: str) -> Iterator[ShardEntry]:
    """List every file under ``area``'s shard folders, in a stable (sorted) order.

    Parameters
    ----------
    area : Path
        Top folder of one kind of file.
    suffix : str
        Suffix of final files (``".h5"``).

    Yields
    ------
    ShardEntry
    """
    if not area.is_dir():
        return
    for top in sorted(area.iterdir()):
        if not top.is_dir():
            yield ShardEntry(None, top, "stray")
            continue
        for sub in sorted(top.iterdir()):
            if not sub.is_dir():
                yield ShardEntry(None, sub, "stray")
                continue
            for path in sorted(sub.iterdir()):
                yield _classify(path, top.name + sub.name, suffix)


def _classify(path: Path, shard: str, suffix: str) -> ShardEntry:
    name = path.name
    stem, mark, _rest = name.partition(_TEMP_MARK)
    is_temp = bool(mark)
    if not stem.endswith(suffix) or not path.is_file():
        return ShardEntry(None, path, "stray")
    uid = stem[: -len(suffix)]
    if not is_uid(uid) or uid[:4] != shard:
        return ShardEntry(None, path, "stray")
    return ShardEntry(uid, path, "temp" if is_temp else "final")
