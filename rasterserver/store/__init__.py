"""The archive's file stores: raw acquisitions (HDF5, write-once) and their helpers.

``layout`` (sharded paths, temp names, scanning), ``durable`` (fsync and no-replace publish)
and ``hashing`` (frame SHA-256) are shared with the derived-results store.
"""

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
