"""The archive's file stores: raw acquisitions (HDF5, write-once) and their helpers.

``layout`` (sharded paths, temp names, scanning), ``durable`` (fsync and no-replace publish)
and ``hashing`` (frame SHA-256) are shared with the derived-results store.

The names below are loaded on first use (PEP 562): importing a light submodule such as
:mod:`rasterserver.store.modes` (the catalogue does, for its lock file) must not load NumPy
and h5py with the package.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rasterserver.store.hashing import frame_sha256
    from rasterserver.store.layout import ShardEntry, is_uid, validate_uid
    from rasterserver.store.raw import (
        DEFAULT_COMPRESSION,
        FileReport,
        FrameProblem,
        FrameToWrite,
        RawStore,
        StoredFrame,
        parse_compression,
    )

#: Public name -> the submodule that defines it.
_HOMES = {
    "frame_sha256": "hashing",
    "ShardEntry": "layout",
    "is_uid": "layout",
    "validate_uid": "layout",
    "DEFAULT_COMPRESSION": "raw",
    "FileReport": "raw",
    "FrameProblem": "raw",
    "FrameToWrite": "raw",
    "RawStore": "raw",
    "StoredFrame": "raw",
    "parse_compression": "raw",
}

__all__ = [
    "DEFAULT_COMPRESSION",
    "FileReport",
    "FrameProblem",
    "FrameToWrite",
    "RawStore",
    "ShardEntry",
    "StoredFrame",
    "frame_sha256",
    "is_uid",
    "parse_compression",
    "validate_uid",
]


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{home}"), name)
