"""The archive's fingerprints: canonical JSON and array bytes, hashed with SHA-256.

The ground floor: imports nothing of rasterserver, and NumPy only when an array is hashed
(the catalogue's readers hash no arrays). Every digest the archive stores is made here:

* documents (calibrations, raster definitions), upload fingerprints and stage parameters:
  :func:`canonical_json` / :func:`canonical_json_sha256` (sorted keys, no whitespace);
* frames: :func:`frame_sha256` (the pixels' bytes, C order, little-endian), which a third
  party can recompute from the HDF5 dataset with
  ``hashlib.sha256(dataset[()].astype("<u2" or "u1").tobytes())``;
* records: :func:`canonical_array` gives the one byte layout their content hash covers.

A digest that changes meaning would make stored provenance lie (a cached result would no
longer be found, or worse, be found for other inputs), so these functions never change
their output; tests pin them.
"""

from __future__ import annotations

import hashlib
import json
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

__all__ = ["canonical", "canonical_array", "canonical_json", "canonical_json_sha256",
           "frame_sha256"]


def canonical_json(document: Any, *, ensure_ascii: bool = True, allow_nan: bool = False) -> str:
    """Serialise ``document`` as canonical JSON: sorted keys, no whitespace.

    Parameters
    ----------
    document : Any
        JSON-serialisable data.
    ensure_ascii : bool, default True
        Escape non-ASCII characters (``\\u00e9``); with False they are written as they are.
        Each kind of digest keeps the choice it was first stored with.
    allow_nan : bool, default False
        Write NaN and infinities as JavaScript does instead of refusing them (ValueError).

    Returns
    -------
    str
    """
    return json.dumps(document, sort_keys=True, separators=(",", ":"),
                      ensure_ascii=ensure_ascii, allow_nan=allow_nan)


def canonical_json_sha256(document: Any, *, ensure_ascii: bool = True,
                          allow_nan: bool = False) -> str:
    """Return the hex SHA-256 of ``document`` as canonical JSON (:func:`canonical_json`).

    Parameters
    ----------
    document : Any
        JSON-serialisable data.
    ensure_ascii, allow_nan : bool
        As for :func:`canonical_json`.

    Returns
    -------
    str
        64 lowercase hex digits.
    """
    text = canonical_json(document, ensure_ascii=ensure_ascii, allow_nan=allow_nan)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def canonical_array(array: np.ndarray) -> np.ndarray:
    """Return ``array`` C-contiguous and little-endian, copying only when it must.

    The one memory layout whose bytes the archive hashes. Like
    :func:`numpy.ascontiguousarray`, it gives a 0-d array one dimension (shape ``(1,)``);
    the record hashes were first stored that way.

    Parameters
    ----------
    array : numpy.ndarray
        Any array.

    Returns
    -------
    numpy.ndarray
        The same values in that layout.
    """
    import numpy as np

    return np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))


#: The name :mod:`rasterserver.store` has always used.
canonical = canonical_array


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
    return hashlib.sha256(canonical_array(array).data).hexdigest()
