"""SHA-256 of a frame: the fingerprint kept in the HDF5 file and in the catalogue.

Defined in :mod:`rasterserver.hashing` (every digest of the archive is made there); this
module keeps the store's names.
"""

from __future__ import annotations

from rasterserver.hashing import canonical, frame_sha256

__all__ = ["canonical", "frame_sha256"]
