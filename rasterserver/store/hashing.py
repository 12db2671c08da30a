"""SHA-256 of a frame: the fingerprint kept in the HDF5 file and in the catalogue.

The digest covers the pixels only: the array's bytes in C order, little-endian. Shape and
dtype are stored beside it, so a third party can recompute it from the HDF5 dataset with
``hashlib.sha256(dataset[()].astype("<u2" or "u1").tobytes())``.
"""

from __future__ import annotations

import hashlib

import numpy as np

__all__ = ["canonical", "frame_sha256"]


def canonical(array: np.ndarray) -> np.ndarray:
    """Return ``array`` C-contiguous and little-endian, copying only when it must.

    Parameters
    ----------
    array : numpy.ndarray
        Any numeric array.

    Returns
    -------
    numpy.ndarray
        The same values in the archive's one memory layout.
    """
    return np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))


def frame_sha256(array: np.ndarray) -> str:
    """Return the hex SHA-256 of a frame's pixels (C order, little-endian).

    Parameters
    ----------
    array : numpy.ndarray
        The frame.

    Returns
    -------
    str
        64 lowercase hex digits.
    """
    # Hashing the buffer directly avoids the copy ``tobytes()`` would make.
    return hashlib.sha256(canonical(array).data).hexdigest()
