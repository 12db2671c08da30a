"""Raw frame store: one write-once HDF5 file per acquisition.

File layout (format version 1)
------------------------------
Path: ``<root>/raw/<uid[0:2]>/<uid[2:4]>/<uid>.h5``, ``uid`` = 32 lowercase hex digits.

Root attributes:

``format``          ``"rasterserver-raw"``
``format_version``  ``1`` (integer)
``uid``             the acquisition uid (string)
``frame_count``     number of datasets under ``/frames`` (integer)
``created_utc``     ISO 8601 time of writing (string)
``writer``          ``"rasterserver <version>"`` (string)

One dataset per frame, ``/frames/<index>`` (``index`` in decimal, no padding): a plain 2-D
``uint8`` or little-endian ``uint16`` dataset, rows x columns, as the camera delivered it.
By default (compression ``"none"``, see BENCHMARKS.md for why) datasets are contiguous, so
any reader can even memory-map them. With compression they are chunked in row bands of about
1 MiB and use a standard HDF5 filter: ``gzip`` (deflate, optionally with ``shuffle``) is built
into every HDF5 library; ``lzf`` is h5py's own and needs h5py (or its plugin) to read.
Dataset attributes:

``index``   frame index within the acquisition (integer, equals the dataset name)
``role``    what the frame shows, e.g. ``"raster"`` or ``"projector-off"`` (string)
``sha256``  hex SHA-256 of the pixels: the array's bytes in C order, little-endian

Strings are HDF5 variable-length UTF-8. Files use the earliest on-disk format versions
(superblock 0), so HDF5 1.8 and later can read them: h5py, HDFView, MATLAB ``h5read`` or
the HDF5 C library read these files without rasterserver.

Durability and write-once
-------------------------
A file is written under ``<uid>.h5.tmp-<pid>-<random>`` in its final folder, closed, fsynced,
then published with a link that fails if the final name exists (see :mod:`.durable`), and the
folder is fsynced. So a final ``.h5`` name always holds a complete file; a crash leaves at
worst a ``*.tmp-*`` file, which :meth:`RawStore.scan` reports.

Locking
-------
Every open passes ``locking=False``. HDF5's own file locks protect concurrent writers of one
file, which cannot happen here (a file is written once, privately, under a temp name, and
never opened for writing again), and ``flock`` fails on many NFS/SMB mounts with "unable to
lock file" errors. Readers therefore never lock; this is safe only because published files
are immutable.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rasterserver import __version__
from rasterserver.errors import ConflictError, InputError, IntegrityError, NotFoundError
from rasterserver.store.durable import ensure_dir, fsync_file, publish
from rasterserver.store.hashing import canonical, frame_sha256
from rasterserver.store.layout import ShardEntry, scan_area, shard_path, temp_path
from rasterserver.store.raw_check import (
    ACCEPTED_DTYPES,
    FORMAT_NAME,
    FileReport,
    FrameProblem,
    attr_text,
    check_raw_file,
    short_error,
)

__all__ = [
    "DEFAULT_COMPRESSION",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "FileReport",
    "FrameProblem",
    "FrameToWrite",
    "RawStore",
    "StoredFrame",
    "parse_compression",
]

FORMAT_VERSION = 1
AREA = "raw"
SUFFIX = ".h5"
# Chosen from benchmarks/store_compression.py (BENCHMARKS.md, "Raw store compression"):
# deflate saves ~25 % on 8-bit frames but writes 4-5x slower, below the ingest target of
# 200 frames/s on a 2-CPU server; camera noise makes frames nearly incompressible.
DEFAULT_COMPRESSION = "none"

_CHUNK_TARGET_BYTES = 1024 * 1024
_COMPRESSION = re.compile(r"(?P<shuffle>shuffle\+)?(?P<codec>none|lzf|gzip)(?:-(?P<level>\d))?")


@dataclass(frozen=True)
class FrameToWrite:
    """One frame handed to :meth:`RawStore.write`.

    Attributes
    ----------
    index : int
        Frame index within the acquisition (>= 0, unique).
    role : str
        What the frame shows, e.g. ``"raster"`` or ``"projector-off"``.
    array : numpy.ndarray
        2-D ``uint8`` or ``uint16`` pixels.
    """

    index: int
    role: str
    array: np.ndarray


@dataclass(frozen=True)
class StoredFrame:
    """Where and what a frame is once stored (what the catalogue records).

    Attributes
    ----------
    index : int
        Frame index within the acquisition.
    role : str
        What the frame shows.
    shape : tuple of int
        ``(rows, columns)``.
    dtype : str
        ``"uint8"`` or ``"uint16"``.
    sha256 : str
        Hex SHA-256 of the pixels (C order, little-endian).
    path : str
        File path relative to the store root, POSIX separators (``raw/ab/cd/<uid>.h5``).
    dataset : str
        HDF5 dataset name (``frames/<index>``).
    """

    index: int
    role: str
    shape: tuple[int, int]
    dtype: str
    sha256: str
    path: str
    dataset: str


def parse_compression(spec: str) -> dict[str, Any]:
    """Translate a compression name into ``h5py.create_dataset`` keyword arguments.

    Parameters
    ----------
    spec : str
        ``"none"``, ``"lzf"``, ``"gzip"`` (level 4) or ``"gzip-<0..9>"``, optionally prefixed
        with ``"shuffle+"`` (byte shuffle before compression; helps ``uint16``).

    Returns
    -------
    dict
        Keyword arguments (``compression``, ``compression_opts``, ``shuffle``).

    Raises
    ------
    InputError
        Unknown specification.
    """
    match = _COMPRESSION.fullmatch(spec)
    if match is None or (match["level"] and match["codec"] != "gzip") or (
        match["shuffle"] and match["codec"] == "none"
    ):
        raise InputError(
            f"unknown compression {spec!r}: use none, lzf, gzip-<level> or shuffle+<codec>"
        )
    codec = match["codec"]
    kwargs: dict[str, Any] = {"shuffle": bool(match["shuffle"])}
    if codec == "gzip":
        kwargs["compression"] = "gzip"
        kwargs["compression_opts"] = int(match["level"] or 4)
    elif codec == "lzf":
        kwargs["compression"] = "lzf"
    return kwargs


class RawStore:
    """Write-once store of raw acquisitions under ``<root>/raw``.

    Parameters
    ----------
    root : Path
        Archive root.
    compression : str, default ``DEFAULT_COMPRESSION``
        See :func:`parse_compression`. Only affects new files; readers need no setting.
    crash_hook : callable, optional
        Called with ``"temp-written"``, ``"fsynced"`` and ``"renamed"`` as :meth:`write`
        passes each step, so a test can kill the process in between. An ``Exception`` raised
        before ``"renamed"`` is treated as an ordinary failure (the temp file is removed); to
        leave the disk exactly as a crash would, call ``os._exit`` or raise a
        ``BaseException`` that is not an ``Exception``.
    """

    def __init__(
        self,
        root: Path,
        *,
        compression: str = DEFAULT_COMPRESSION,
        crash_hook: Callable[[str], None] | None = None,
    ) -> None:
        self.root = Path(root)
        self.area = self.root / AREA
        self.compression = compression
        self._filters = parse_compression(compression)
        self._crash_hook = crash_hook

    # --- paths -------------------------------------------------------------------------------

    def path_for(self, uid: str) -> Path:
        """Return the final path of acquisition ``uid`` (whether or not it exists).

        Parameters
        ----------
        uid : str
            Acquisition uid (32 lowercase hex digits).

        Returns
        -------
        Path
        """
        return shard_path(self.area, uid, SUFFIX)

    def relative_path(self, uid: str) -> str:
        """Return the path of ``uid`` relative to the store root, with POSIX separators."""
        return self.path_for(uid).relative_to(self.root).as_posix()

    def exists(self, uid: str) -> bool:
        """Return True if the published file of ``uid`` exists."""
        return self.path_for(uid).is_file()

    # --- writing -----------------------------------------------------------------------------

    def write(self, uid: str, frames: Sequence[FrameToWrite]) -> list[StoredFrame]:
        """Write all frames of one acquisition as a new file, durably and atomically.

        Parameters
        ----------
        uid : str
            Acquisition uid (32 lowercase hex digits), chosen by the caller.
        frames : sequence of FrameToWrite
            At least one frame; indices unique.

        Returns
        -------
        list of StoredFrame
            One per frame, in the order given.

        Raises
        ------
        InputError
            No frames, duplicate indices, an empty role or a frame that is not a non-empty
            2-D ``uint8``/``uint16`` array.
        ConflictError
            A file for ``uid`` already exists (files are write-once).
        """
        final = self.path_for(uid)
        prepared = _prepare(frames)
        if final.exists():
            raise ConflictError(f"raw file of {uid} already exists; archive files are write-once")
        ensure_dir(final.parent)
        relative = self.relative_path(uid)
        temp = temp_path(final)
        stored: list[StoredFrame] = []
        try:
            # libver="earliest": the oldest on-disk format that can hold the file, so that
            # HDF5 1.8 readers (old MATLAB, HDFView) open it too.
            with h5py.File(temp, "w-", libver="earliest", locking=False) as h5:
                h5.attrs["format"] = FORMAT_NAME
                h5.attrs["format_version"] = np.int64(FORMAT_VERSION)
                h5.attrs["uid"] = uid
                h5.attrs["frame_count"] = np.int64(len(prepared))
                h5.attrs["created_utc"] = datetime.now(UTC).isoformat(timespec="seconds")
                h5.attrs["writer"] = f"rasterserver {__version__}"
                group = h5.create_group("frames")
                for frame, array in prepared:
                    digest = frame_sha256(array)
                    name = str(frame.index)
                    dataset = group.create_dataset(
                        name, data=array, **self._layout(array)
                    )
                    dataset.attrs["index"] = np.int64(frame.index)
                    dataset.attrs["role"] = frame.role
                    dataset.attrs["sha256"] = digest
                    stored.append(StoredFrame(
                        index=frame.index, role=frame.role,
                        shape=(int(array.shape[0]), int(array.shape[1])),
                        dtype=array.dtype.name, sha256=digest, path=relative,
                        dataset=f"frames/{name}",
                    ))
            self._step("temp-written")
            fsync_file(temp)
            self._step("fsynced")
            publish(temp, final)
        except Exception:
            # An orderly failure (full disk, conflict, bad data) leaves nothing behind; a real
            # crash cannot run this and leaves the temp file for `verify` to report.
            temp.unlink(missing_ok=True)
            raise
        self._step("renamed")
        return stored

    def _layout(self, array: np.ndarray) -> dict[str, Any]:
        if "compression" not in self._filters and not self._filters["shuffle"]:
            return {}  # contiguous: the simplest layout for other readers
        rows, cols = array.shape
        band = max(1, min(rows, _CHUNK_TARGET_BYTES // (cols * array.dtype.itemsize)))
        return {"chunks": (band, cols), **self._filters}

    def _step(self, name: str) -> None:
        if self._crash_hook is not None:
            self._crash_hook(name)

    # --- reading -----------------------------------------------------------------------------

    def frames(self, uid: str) -> list[StoredFrame]:
        """Describe the frames of ``uid`` from the file's attributes, without reading pixels.

        Parameters
        ----------
        uid : str
            Acquisition uid.

        Returns
        -------
        list of StoredFrame
            Sorted by index.

        Raises
        ------
        NotFoundError
            No file for ``uid``.
        IntegrityError
            The file cannot be read.
        """
        relative = self.relative_path(uid)
        out = []
        with self._open(uid) as h5:
            for index, dataset in _datasets(h5, relative):
                out.append(StoredFrame(
                    index=index, role=attr_text(dataset.attrs.get("role", "")),
                    shape=(int(dataset.shape[0]), int(dataset.shape[1])),
                    dtype=dataset.dtype.name, sha256=attr_text(dataset.attrs.get("sha256", "")),
                    path=relative, dataset=f"frames/{index}",
                ))
        return out

    def read(self, uid: str, index: int, *, verify: bool = True) -> np.ndarray:
        """Read one frame.

        Parameters
        ----------
        uid : str
            Acquisition uid.
        index : int
            Frame index.
        verify : bool, default True
            Recompute the SHA-256 and compare it with the stored one (about 1 ms per
            megabyte); a silently corrupted frame must not reach a measurement.

        Returns
        -------
        numpy.ndarray
            Read-only, C-contiguous 2-D array.

        Raises
        ------
        NotFoundError
            No file for ``uid``, or no frame ``index`` in it.
        IntegrityError
            The frame cannot be decoded or its hash differs from the stored one.
        """
        relative = self.relative_path(uid)
        with self._open(uid) as h5:
            dataset = h5.get(f"frames/{int(index)}")
            if not isinstance(dataset, h5py.Dataset):
                raise NotFoundError(f"{relative}: no frame {index}")
            return _load(dataset, relative, int(index), verify)

    def read_all(self, uid: str, *, verify: bool = True) -> dict[int, np.ndarray]:
        """Read every frame of ``uid``.

        Parameters
        ----------
        uid : str
            Acquisition uid.
        verify : bool, default True
            As for :meth:`read`.

        Returns
        -------
        dict of int to numpy.ndarray
            Read-only arrays keyed and ordered by frame index.

        Raises
        ------
        NotFoundError, IntegrityError
            As for :meth:`read`.
        """
        relative = self.relative_path(uid)
        with self._open(uid) as h5:
            return {
                index: _load(dataset, relative, index, verify)
                for index, dataset in _datasets(h5, relative)
            }

    def _open(self, uid: str) -> h5py.File:
        path = self.path_for(uid)
        if not path.is_file():
            raise NotFoundError(f"no raw file for acquisition {uid}")
        try:
            return h5py.File(path, "r", locking=False)
        except OSError as exc:
            raise IntegrityError(
                f"{self.relative_path(uid)}: unreadable HDF5 file ({short_error(exc)})"
            ) from None

    # --- verification ------------------------------------------------------------------------

    def scan(self) -> Iterator[ShardEntry]:
        """List every file under ``<root>/raw``, sorted.

        Yields
        ------
        ShardEntry
            ``kind="final"`` for published files, ``"temp"`` for leftover partial writes
            (with the uid they were for), ``"stray"`` for anything else.
        """
        return scan_area(self.area, SUFFIX)

    def check_file(self, uid: str, expected: Mapping[int, str] | None = None) -> FileReport:
        """Re-read and re-hash every frame of ``uid``.

        Parameters
        ----------
        uid : str
            Acquisition uid.
        expected : mapping of int to str, optional
            Frame index to SHA-256 as the catalogue records them. When given, frames absent
            from it are ``extra-frame``, indices absent from the file ``missing-frame``, and
            pixels hashing differently ``catalog-mismatch``.

        Returns
        -------
        FileReport
        """
        return check_raw_file(self.path_for(uid), uid, self.relative_path(uid), expected)


# --- helpers -----------------------------------------------------------------------------------


def _prepare(frames: Sequence[FrameToWrite]) -> list[tuple[FrameToWrite, np.ndarray]]:
    """Validate frames before anything touches the disk."""
    if not frames:
        raise InputError("an acquisition needs at least one frame")
    seen: set[int] = set()
    out = []
    for frame in frames:
        index = frame.index
        if isinstance(index, bool) or not isinstance(index, int | np.integer) or index < 0:
            raise InputError(f"frame index {index!r} must be a non-negative integer")
        if index in seen:
            raise InputError(f"frame index {index} appears twice")
        seen.add(int(index))
        if not isinstance(frame.role, str) or not frame.role.strip():
            raise InputError(f"frame {index}: role must be a non-empty string")
        array = np.asarray(frame.array)
        if array.ndim != 2 or 0 in array.shape:
            raise InputError(f"frame {index}: shape {array.shape} is not a non-empty 2-D frame")
        if array.dtype.newbyteorder("=") not in ACCEPTED_DTYPES:
            raise InputError(f"frame {index}: dtype {array.dtype.name} is not uint8 or uint16")
        out.append((FrameToWrite(int(index), frame.role, frame.array), canonical(array)))
    return out


def _datasets(h5: h5py.File, relative: str) -> list[tuple[int, h5py.Dataset]]:
    """Frame datasets of an open file, sorted by index; IntegrityError if malformed."""
    group = h5.get("frames")
    if not isinstance(group, h5py.Group) or h5.attrs.get("format") != FORMAT_NAME:
        raise IntegrityError(f"{relative}: not a rasterserver raw file")
    out = []
    for name, item in group.items():
        if not name.isdigit() or not isinstance(item, h5py.Dataset):
            raise IntegrityError(f"{relative}: unexpected entry frames/{name}")
        out.append((int(name), item))
    return sorted(out, key=lambda pair: pair[0])


def _load(dataset: h5py.Dataset, relative: str, index: int, verify: bool) -> np.ndarray:
    try:
        array = canonical(dataset[()])
    except (OSError, ValueError) as exc:
        raise IntegrityError(
            f"{relative}: frame {index} is unreadable ({short_error(exc)})") from None
    if verify and frame_sha256(array) != attr_text(dataset.attrs.get("sha256", "")):
        raise IntegrityError(f"{relative}: frame {index} does not match its SHA-256")
    array.flags.writeable = False
    return array
