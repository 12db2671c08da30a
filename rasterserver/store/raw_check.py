"""Re-checking a raw acquisition file: every frame re-read and re-hashed (``verify``).

What :meth:`rasterserver.store.raw.RawStore.check_file` reports, frame by frame, and the
few facts of the raw file format that reading and checking share.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import h5py
import numpy as np

from rasterserver.hashing import frame_sha256

__all__ = ["ACCEPTED_DTYPES", "FORMAT_NAME", "FileReport", "FrameProblem", "ProblemKind",
           "attr_text", "check_raw_file", "short_error"]

#: The ``format`` attribute of every raw file.
FORMAT_NAME = "rasterserver-raw"
#: The pixel types a raw frame may have.
ACCEPTED_DTYPES = (np.dtype("uint8"), np.dtype("uint16"))


ProblemKind = Literal[
    "missing-file",
    "unreadable-file",
    "bad-attributes",
    "unreadable-frame",
    "hash-mismatch",
    "catalog-mismatch",
    "missing-frame",
    "extra-frame",
]


@dataclass(frozen=True)
class FrameProblem:
    """One inconsistency found by :func:`check_raw_file`.

    Attributes
    ----------
    kind : str
        ``missing-file``, ``unreadable-file`` (not an HDF5 file, truncated),
        ``bad-attributes`` (not a rasterserver raw file, or attributes disagree with the
        content), ``unreadable-frame`` (a dataset cannot be decoded), ``hash-mismatch``
        (pixels differ from the file's own ``sha256``), ``catalog-mismatch`` (pixels differ
        from the expected hash), ``missing-frame`` (expected but absent), ``extra-frame``
        (present but not expected).
    index : int or None
        Frame concerned, if any.
    message : str
        Human-readable explanation (no absolute paths).
    """

    kind: ProblemKind
    index: int | None
    message: str


@dataclass(frozen=True)
class FileReport:
    """Result of re-checking one raw file.

    Attributes
    ----------
    uid : str
        Acquisition uid.
    path : str
        File path relative to the store root.
    status : {"ok", "missing", "unreadable", "corrupt"}
        ``missing``: no file. ``unreadable``: the file cannot be opened as a rasterserver raw
        file. ``corrupt``: it opens but at least one frame is wrong, missing or extra.
    problems : tuple of FrameProblem
        Everything found; empty when ``status == "ok"``.
    hashes : dict of int to str
        SHA-256 recomputed from the pixels of each readable frame.
    """

    uid: str
    path: str
    status: Literal["ok", "missing", "unreadable", "corrupt"]
    problems: tuple[FrameProblem, ...] = ()
    hashes: dict[int, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """True when the file is complete and every frame matches its hashes."""
        return self.status == "ok"


def check_raw_file(path: Path, uid: str, relative: str,
                   expected: Mapping[int, str] | None = None) -> FileReport:
    """Re-read and re-hash every frame of the raw file at ``path``.

    Parameters
    ----------
    path : Path
        The file.
    uid : str
        The acquisition it should hold.
    relative : str
        Its path inside the store, for messages (no absolute paths).
    expected : mapping of int to str, optional
        As for :meth:`~rasterserver.store.raw.RawStore.check_file`.

    Returns
    -------
    FileReport
    """
    if not path.is_file():
        return FileReport(uid, relative, "missing", (
            FrameProblem("missing-file", None, f"{relative}: file is missing"),
        ))
    try:
        h5 = h5py.File(path, "r", locking=False)
    except OSError as exc:
        return FileReport(uid, relative, "unreadable", (FrameProblem(
            "unreadable-file", None, f"{relative}: not a readable HDF5 file ({short_error(exc)})"
        ),))
    with h5:
        try:
            return _check_open_file(h5, uid, relative, expected)
        except (OSError, KeyError, RuntimeError) as exc:
            # Metadata damaged beyond a single dataset (the group's index, say).
            return FileReport(uid, relative, "unreadable", (FrameProblem(
                "unreadable-file", None, f"{relative}: damaged HDF5 structure ({short_error(exc)})"
            ),))


def _check_open_file(
    h5: h5py.File, uid: str, relative: str, expected: Mapping[int, str] | None
) -> FileReport:
    problems: list[FrameProblem] = []
    hashes: dict[int, str] = {}
    attrs = h5.attrs
    group = h5.get("frames")
    if attrs.get("format") != FORMAT_NAME or not isinstance(group, h5py.Group):
        return FileReport(uid, relative, "unreadable", (FrameProblem(
            "bad-attributes", None, f"{relative}: not a rasterserver raw file"
        ),))
    if attr_text(attrs.get("uid", "")) != uid:
        problems.append(FrameProblem(
            "bad-attributes", None,
            f"{relative}: file says uid {attr_text(attrs.get('uid', ''))!r}, expected {uid}",
        ))
    names = list(group.keys())
    if attrs.get("frame_count") != len(names):
        problems.append(FrameProblem(
            "bad-attributes", None,
            f"{relative}: frame_count is {attrs.get('frame_count')} but the file holds "
            f"{len(names)} frames",
        ))
    present: set[int] = set()
    for name in names:
        if not name.isdigit():
            problems.append(FrameProblem(
                "extra-frame", None, f"{relative}: unexpected entry frames/{name}"
            ))
            continue
        index = int(name)
        present.add(index)
        problems.extend(_check_frame(group, name, index, relative, hashes))
        if expected is not None and index in hashes:
            if index not in expected:
                problems.append(FrameProblem(
                    "extra-frame", index, f"{relative}: frame {index} is not in the catalogue"
                ))
            elif hashes[index] != expected[index]:
                problems.append(FrameProblem(
                    "catalog-mismatch", index,
                    f"{relative}: frame {index} differs from the catalogue's SHA-256",
                ))
    if expected is not None:
        for index in sorted(set(expected) - present):
            problems.append(FrameProblem(
                "missing-frame", index, f"{relative}: frame {index} is missing"
            ))
    status: Literal["ok", "corrupt"] = "corrupt" if problems else "ok"
    return FileReport(uid, relative, status, tuple(problems), hashes)


def _check_frame(
    group: h5py.Group, name: str, index: int, relative: str, hashes: dict[int, str]
) -> list[FrameProblem]:
    item = group.get(name)
    if not isinstance(item, h5py.Dataset):
        return [FrameProblem("extra-frame", index, f"{relative}: frames/{name} is not a dataset")]
    problems = []
    try:
        array = item[()]
    except (OSError, ValueError) as exc:
        return [FrameProblem(
            "unreadable-frame", index,
            f"{relative}: frame {index} is unreadable ({short_error(exc)})",
        )]
    if array.ndim != 2 or array.dtype.newbyteorder("=") not in ACCEPTED_DTYPES:
        problems.append(FrameProblem(
            "bad-attributes", index,
            f"{relative}: frame {index} is {array.dtype} of shape {array.shape}, not a frame",
        ))
    digest = frame_sha256(array)
    hashes[index] = digest
    stored = attr_text(item.attrs.get("sha256", ""))
    if digest != stored:
        problems.append(FrameProblem(
            "hash-mismatch", index,
            f"{relative}: frame {index} does not match its stored SHA-256",
        ))
    if item.attrs.get("index") != index:
        problems.append(FrameProblem(
            "bad-attributes", index, f"{relative}: frame {index} has index attribute "
            f"{item.attrs.get('index')!r}",
        ))
    return problems


def attr_text(value: object) -> str:
    """An HDF5 string attribute as text (h5py gives bytes or str)."""
    return value.decode() if isinstance(value, bytes) else str(value)


def short_error(exc: BaseException) -> str:
    """First line of an HDF5 error, without the absolute path h5py likes to include."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return re.sub(r"(name|filename) = '[^']*'", r"\1 = <file>", text)[:200]

