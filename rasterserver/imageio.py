"""Decoding and validation of input frames (PNG, TIFF, NPY and raw pixel dumps).

A frame is one camera image: a 2-D ``uint8`` or ``uint16`` matrix, rows x columns (portrait
camera, e.g. 604 x 576, up to 2448 x 2048). Everything that is not exactly that is refused with
an :class:`~rasterserver.errors.InputError` whose message names the file (its base name only:
patient folders must not reach logs) and says what is wrong.

Formats are recognised by their content (magic bytes), not by their extension, except raw
dumps, which have no signature:

``PNG`` and ``TIFF``
    Decoded with OpenCV (``cv2.imdecode(..., IMREAD_UNCHANGED)``), 8 or 16 bit, one page.
    The image size is read from the header *before* decoding so that a small file declaring a
    huge image (a decompression bomb) is refused without allocating it.
``NPY``
    ``np.load(allow_pickle=False)``; the header is checked before the data are read.
raw (``.raw`` / ``.bin``, or any unrecognised content when ``shape`` and ``dtype`` are given)
    Pixels in C order with no header; the size must be exactly rows x columns x itemsize.
    ``uint16`` raw data are little-endian unless ``dtype`` says ``">u2"``.

Decisions worth knowing:

* Colour images (3 channels) are refused unless ``convert_color=True``, even when the three
  channels are equal: a camera that writes grey as BGR is misconfigured and someone should
  notice. With ``convert_color=True`` they are converted with ``cv2.COLOR_BGR2GRAY``, keeping
  the bit depth.
* Images with an alpha channel (2 or 4 channels) are always refused: transparency has no
  meaning for a camera frame and silently dropping it could hide pixels.
* JPEG is refused: it is lossy, and the archive keeps the camera's pixels exactly.
* If ``shape`` or ``dtype`` are given for a self-describing format they are *expectations*:
  a decoded frame of another shape or dtype is refused.
* Frames are returned C-contiguous, little-endian (native on every supported platform) and
  read-only: raw frames are never modified after ingest.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path

import cv2
import numpy as np

from rasterserver.errors import InputError

__all__ = ["DEFAULT_MAX_BYTES", "decode_frame_bytes", "read_frame"]

DEFAULT_MAX_BYTES = 256 * 1024 * 1024

_ACCEPTED_DTYPES = (np.dtype("uint8"), np.dtype("uint16"))
_RAW_SUFFIXES = frozenset({".raw", ".bin"})

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*")
_BIGTIFF_MAGICS = (b"II+\x00", b"MM\x00+")
_NPY_MAGIC = b"\x93NUMPY"
_JPEG_MAGIC = b"\xff\xd8\xff"

# TIFF tags read from the first directory (TIFF 6.0 specification).
_TAG_WIDTH, _TAG_LENGTH, _TAG_BITS, _TAG_SAMPLES = 256, 257, 258, 277
# Bound on the IFD chain walked to count pages: a cyclic chain must not loop forever.
_MAX_TIFF_PAGES = 10_000


def _file_size_limit(max_bytes: int) -> int:
    """Largest *file* worth reading for a frame of at most ``max_bytes`` decoded bytes.

    An uncompressed TIFF or an incompressible PNG is slightly larger than its pixels, so the
    file limit leaves room for the container; the decoded size is checked exactly later.
    """
    return max_bytes + max_bytes // 8 + 1024 * 1024


def read_frame(
    path: Path,
    *,
    shape: tuple[int, int] | None = None,
    dtype: str | None = None,
    convert_color: bool = False,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> np.ndarray:
    """Read and validate one frame from a file.

    Parameters
    ----------
    path : Path
        File to read (PNG, TIFF, NPY or raw).
    shape : tuple of int, optional
        ``(rows, columns)``. Required for raw files; for other formats, the expected shape.
    dtype : str, optional
        ``"uint8"`` or ``"uint16"`` (or an explicit-endian form such as ``">u2"``). Required
        for raw files; for other formats, the expected dtype.
    convert_color : bool, default False
        Convert 3-channel (BGR) images to grey instead of refusing them.
    max_bytes : int, default 256 MiB
        Largest decoded frame accepted, in bytes.

    Returns
    -------
    numpy.ndarray
        A read-only, C-contiguous 2-D ``uint8`` or ``uint16`` array.

    Raises
    ------
    InputError
        The file is missing, empty, truncated, not an image, too large, or not a 2-D
        ``uint8``/``uint16`` grey frame.
    """
    path = Path(path)
    name = path.name
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise InputError(f"{name}: no such file") from None
    except OSError as exc:
        raise InputError(f"{name}: cannot be read ({exc.strerror})") from None
    if not path.is_file():
        raise InputError(f"{name}: not a regular file")
    # Checked before reading: the file is about to be held in memory as a whole.
    if size > _file_size_limit(max_bytes):
        raise InputError(
            f"{name}: file of {size} bytes is larger than the frame limit of {max_bytes} bytes"
        )
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{name}: cannot be read ({exc.strerror})") from None
    return decode_frame_bytes(
        data, name=name, shape=shape, dtype=dtype, convert_color=convert_color,
        max_bytes=max_bytes,
    )


def decode_frame_bytes(
    data: bytes,
    *,
    name: str,
    shape: tuple[int, int] | None = None,
    dtype: str | None = None,
    convert_color: bool = False,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> np.ndarray:
    """Decode and validate one frame held in memory (an upload, or a file's content).

    Parameters
    ----------
    data : bytes
        The file's content.
    name : str
        File name used in messages and to recognise raw files by their extension
        (``.raw``/``.bin``). Only its base name is ever shown.
    shape, dtype, convert_color, max_bytes
        As for :func:`read_frame`.

    Returns
    -------
    numpy.ndarray
        A read-only, C-contiguous 2-D ``uint8`` or ``uint16`` array.

    Raises
    ------
    InputError
        As for :func:`read_frame`.
    """
    # A caller may pass a full path as the name; messages keep only the base name.
    name = Path(name).name or "frame"
    expected_dtype = _parse_dtype(dtype, name) if dtype is not None else None
    if shape is not None:
        shape = _parse_shape(shape, name)
    if len(data) == 0:
        raise InputError(f"{name}: empty file")
    if len(data) > _file_size_limit(max_bytes):
        raise InputError(
            f"{name}: {len(data)} bytes is larger than the frame limit of {max_bytes} bytes"
        )

    head = bytes(data[:8])
    suffix = Path(name).suffix.lower()
    if suffix in _RAW_SUFFIXES:
        array = _decode_raw(data, name, shape, expected_dtype)
    elif head.startswith(_PNG_MAGIC):
        array = _decode_png(data, name, convert_color, max_bytes)
    elif head.startswith(_TIFF_MAGICS):
        array = _decode_tiff(data, name, convert_color, max_bytes)
    elif head.startswith(_BIGTIFF_MAGICS):
        raise InputError(f"{name}: BigTIFF is not supported; save the frame as a plain TIFF")
    elif head.startswith(_NPY_MAGIC):
        array = _decode_npy(data, name, max_bytes)
    elif head.startswith(_JPEG_MAGIC):
        raise InputError(
            f"{name}: JPEG is lossy and not accepted; save the frame as PNG, TIFF or NPY"
        )
    elif shape is not None and expected_dtype is not None:
        array = _decode_raw(data, name, shape, expected_dtype)
    else:
        raise InputError(
            f"{name}: not an image (unrecognised content); accepted formats are PNG, TIFF, "
            "NPY, and raw pixels (.raw/.bin) with a shape and dtype"
        )
    return _finish(array, name, shape, expected_dtype, max_bytes)


# --- parameter parsing -----------------------------------------------------------------------


def _parse_dtype(dtype: str, name: str) -> np.dtype:
    try:
        parsed = np.dtype(dtype)
    except TypeError:
        raise InputError(f"{name}: unknown dtype {dtype!r}; use uint8 or uint16") from None
    if parsed.newbyteorder("=") not in _ACCEPTED_DTYPES:
        raise InputError(f"{name}: dtype {dtype!r} is not accepted; use uint8 or uint16")
    # "uint16" is native order; raw frames are defined as little-endian, whatever the host.
    return parsed.newbyteorder("<") if parsed.byteorder == "=" else parsed


def _parse_shape(shape: tuple[int, int], name: str) -> tuple[int, int]:
    if len(shape) != 2:
        raise InputError(f"{name}: shape {tuple(shape)} must be (rows, columns)")
    rows, cols = (int(n) for n in shape)
    if rows <= 0 or cols <= 0:
        raise InputError(f"{name}: shape {(rows, cols)} must be positive")
    return rows, cols


# --- per-format decoders ---------------------------------------------------------------------


def _decode_raw(
    data: bytes, name: str, shape: tuple[int, int] | None, dtype: np.dtype | None
) -> np.ndarray:
    if shape is None or dtype is None:
        raise InputError(
            f"{name}: raw pixel file needs a shape and a dtype (e.g. 604x576 uint16)"
        )
    expected = shape[0] * shape[1] * dtype.itemsize
    if len(data) != expected:
        raise InputError(
            f"{name}: raw file is {len(data)} bytes but {shape[0]}x{shape[1]} {dtype.name} "
            f"needs exactly {expected} bytes"
        )
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def _check_declared_size(
    name: str, rows: int, cols: int, channels: int, itemsize: int, max_bytes: int
) -> None:
    """Refuse, before decoding, an image whose header declares more than ``max_bytes``."""
    if rows <= 0 or cols <= 0:
        raise InputError(f"{name}: image has a zero-size dimension ({rows}x{cols})")
    declared = rows * cols * max(channels, 1) * max(itemsize, 1)
    if declared > max_bytes:
        raise InputError(
            f"{name}: image of {rows}x{cols} pixels ({declared} bytes decoded) is larger than "
            f"the frame limit of {max_bytes} bytes"
        )


def _decode_png(data: bytes, name: str, convert_color: bool, max_bytes: int) -> np.ndarray:
    # IHDR is always the first chunk: length(4) type(4) width(4) height(4) depth(1) colour(1).
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise InputError(f"{name}: truncated or corrupt PNG (no image header)")
    cols, rows, depth, colour_type = struct.unpack(">IIBB", data[16:26])
    channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(colour_type, 4)
    _check_declared_size(name, rows, cols, channels, 2 if depth == 16 else 1, max_bytes)
    # OpenCV 5 returns None for truncated PNGs; the IEND check keeps that guarantee
    # independent of the decoder build (some decoders return the rows read so far).
    if data.rfind(b"IEND") < 0:
        raise InputError(f"{name}: truncated PNG (no end chunk)")
    return _imdecode(data, name, "PNG", convert_color)


def _decode_tiff(data: bytes, name: str, convert_color: bool, max_bytes: int) -> np.ndarray:
    rows, cols, bits, samples, pages = _tiff_header(data, name)
    if pages > 1:
        raise InputError(
            f"{name}: multi-page TIFF ({pages} pages); a frame file must hold one image"
        )
    _check_declared_size(name, rows, cols, samples, (bits + 7) // 8, max_bytes)
    return _imdecode(data, name, "TIFF", convert_color)


def _tiff_header(data: bytes, name: str) -> tuple[int, int, int, int, int]:
    """Return rows, columns, bits per sample, samples per pixel and page count of a TIFF."""
    order = "<" if data[:2] == b"II" else ">"
    truncated = InputError(f"{name}: truncated or corrupt TIFF (directory out of the file)")
    try:
        (offset,) = struct.unpack_from(order + "I", data, 4)
        first: dict[int, int] = {}
        pages = 0
        seen: set[int] = set()
        while offset and pages < _MAX_TIFF_PAGES:
            if offset in seen:
                raise InputError(f"{name}: corrupt TIFF (directory chain loops)")
            seen.add(offset)
            (count,) = struct.unpack_from(order + "H", data, offset)
            if pages == 0:
                for i in range(count):
                    tag, typ, n, raw = struct.unpack_from(
                        order + "HHI4s", data, offset + 2 + 12 * i
                    )
                    if typ not in (3, 4):  # only SHORT and LONG tags are needed here
                        continue
                    fmt = order + ("H" if typ == 3 else "I")
                    if n * struct.calcsize(fmt) <= 4:
                        # Small values sit left-justified in the 4-byte value field.
                        first[tag] = struct.unpack_from(fmt, raw)[0]
                    else:
                        # Larger ones (e.g. BitsPerSample of RGB) are stored at an offset.
                        (where,) = struct.unpack_from(order + "I", raw)
                        first[tag] = struct.unpack_from(fmt, data, where)[0]
            (offset,) = struct.unpack_from(order + "I", data, offset + 2 + 12 * count)
            pages += 1
    except struct.error:
        raise truncated from None
    if _TAG_WIDTH not in first or _TAG_LENGTH not in first:
        raise InputError(f"{name}: corrupt TIFF (no image width or length)")
    return (
        first[_TAG_LENGTH], first[_TAG_WIDTH], first.get(_TAG_BITS, 1),
        first.get(_TAG_SAMPLES, 1), pages,
    )


def _imdecode(data: bytes, name: str, fmt: str, convert_color: bool) -> np.ndarray:
    buffer = np.frombuffer(data, dtype=np.uint8)
    # IMREAD_UNCHANGED keeps the bit depth and the channels and ignores EXIF orientation:
    # the pixels come back exactly as stored, never rotated or reduced to 8 bits.
    try:
        image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        image = None
    if image is None:
        raise InputError(f"{name}: truncated or corrupt {fmt} (the decoder could not read it)")
    if image.ndim == 3:
        image = _to_grey(image, name, convert_color)
    return image


def _to_grey(image: np.ndarray, name: str, convert_color: bool) -> np.ndarray:
    channels = image.shape[2]
    if channels == 1:
        return image[:, :, 0]
    if channels in (2, 4):
        raise InputError(
            f"{name}: image has an alpha channel ({channels} channels); save the frame as a "
            "grey image without transparency"
        )
    if channels != 3:
        raise InputError(f"{name}: image has {channels} channels; a frame must be grey")
    if not convert_color:
        equal = bool((image[:, :, 0] == image[:, :, 1]).all()
                     and (image[:, :, 1] == image[:, :, 2]).all())
        hint = " whose channels are all equal" if equal else ""
        raise InputError(
            f"{name}: colour image (3 channels){hint}; pass --convert-color to convert it "
            "to grey"
        )
    # cvtColor keeps 16-bit depth; BGR is OpenCV's channel order after imdecode.
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def _decode_npy(data: bytes, name: str, max_bytes: int) -> np.ndarray:
    stream = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(stream)
        header_reader = {
            (1, 0): np.lib.format.read_array_header_1_0,
            (2, 0): np.lib.format.read_array_header_2_0,
        }.get(version)
        if header_reader is None:
            raise InputError(f"{name}: NPY format version {version} is not supported")
        shape, _fortran, dtype = header_reader(stream)
    except ValueError as exc:
        raise InputError(f"{name}: corrupt NPY header ({exc})") from None
    _check_array_kind(name, shape, dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if nbytes > max_bytes:
        raise InputError(
            f"{name}: array of {nbytes} bytes is larger than the frame limit of "
            f"{max_bytes} bytes"
        )
    stream.seek(0)
    try:
        array = np.load(stream, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(f"{name}: truncated or corrupt NPY ({exc})") from None
    return array


def _check_array_kind(name: str, shape: tuple[int, ...], dtype: np.dtype) -> None:
    """Refuse an NPY array by its header alone: wrong dimensions or dtype."""
    if dtype.hasobject:
        raise InputError(f"{name}: NPY holds Python objects; a frame must be uint8 or uint16")
    if len(shape) != 2:
        raise InputError(
            f"{name}: {len(shape)}-D array of shape {tuple(shape)}; a frame must be a 2-D "
            "grey image (rows, columns)"
        )
    if dtype.newbyteorder("=") not in _ACCEPTED_DTYPES:
        raise InputError(
            f"{name}: dtype {dtype.name} is not accepted; a frame must be uint8 or uint16"
        )


# --- common validation -----------------------------------------------------------------------


def _finish(
    array: np.ndarray,
    name: str,
    shape: tuple[int, int] | None,
    dtype: np.dtype | None,
    max_bytes: int,
) -> np.ndarray:
    if array.ndim != 2:
        raise InputError(
            f"{name}: {array.ndim}-D data of shape {array.shape}; a frame must be a 2-D grey "
            "image (rows, columns)"
        )
    if array.dtype.newbyteorder("=") not in _ACCEPTED_DTYPES:
        raise InputError(
            f"{name}: pixel type {array.dtype.name} is not accepted; a frame must be uint8 "
            "or uint16"
        )
    if 0 in array.shape:
        raise InputError(f"{name}: frame has a zero-size dimension {array.shape}")
    if array.nbytes > max_bytes:
        raise InputError(
            f"{name}: frame of {array.nbytes} bytes is larger than the frame limit of "
            f"{max_bytes} bytes"
        )
    if shape is not None and array.shape != shape:
        raise InputError(
            f"{name}: frame is {array.shape[0]}x{array.shape[1]} but "
            f"{shape[0]}x{shape[1]} was expected"
        )
    if dtype is not None and array.dtype.newbyteorder("=") != dtype.newbyteorder("="):
        raise InputError(f"{name}: frame is {array.dtype.name} but {dtype.name} was expected")
    # One canonical memory layout, so the archive's SHA-256 of a frame is host-independent.
    out = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))
    out.flags.writeable = False
    return out
