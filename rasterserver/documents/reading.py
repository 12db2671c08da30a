"""JSON text (a file, bytes or a string) to a Python value, with a sentence instead of a
traceback for every way a file can fail to be a document."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from rasterserver.errors import InputError

#: A calibration is a few kilobytes, with an inline raster some tens: anything this large is
#: not one (and is not read into memory whole to find that out).
MAX_DOCUMENT_BYTES = 4 * 1024 * 1024


def json_kind(value: Any) -> str:
    """What a JSON value is, in words (``an array``), for a refusal."""
    if isinstance(value, list):
        return "an array"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, bool) or value is None:
        return json.dumps(value)
    return "a number"


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    document = dict(pairs)
    if len(document) != len(pairs):
        seen: set[str] = set()
        twice = next(k for k, _ in pairs if k in seen or seen.add(k))  # type: ignore[func-returns-value]
        raise InputError(f"the key {twice!r} appears twice in one object")
    return document


def read_document(data: str | bytes | Path, *, what: str, source: str | None = None) -> Any:
    """Parse a JSON document from a file, bytes or text, with a sentence for every failure.

    Parameters
    ----------
    data : str, bytes or Path
        A file, its bytes, or JSON text.
    what : str
        What the document should be (``"calibration"``), for messages.
    source : str, optional
        How messages name it; the file's name by default.

    Returns
    -------
    Any
        The parsed value (not yet checked to be an object).

    Raises
    ------
    InputError
        No such file, a directory, unreadable, too large, not UTF-8, not JSON, nested too
        deeply, or a key twice in one object.
    """
    if isinstance(data, Path):
        source = source or data.name or str(data)
        if data.is_dir():
            raise InputError(f"{source}: is a directory, not a {what} file")
        try:
            with data.open("rb") as fh:
                data = fh.read(MAX_DOCUMENT_BYTES + 1)
        except FileNotFoundError:
            raise InputError(f"{source}: no such {what} file") from None
        except OSError as exc:
            raise InputError(f"{source}: cannot read the {what} file ({exc.strerror})") from None
    source = source or what
    if len(data) > MAX_DOCUMENT_BYTES:
        raise InputError(
            f"{source}: larger than {MAX_DOCUMENT_BYTES // (1024 * 1024)} MiB, too large for a "
            f"{what} document"
        )
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8-sig")  # a byte-order mark from a Windows editor is fine
        except UnicodeDecodeError as exc:
            raise InputError(
                f"{source}: not a JSON {what}: not UTF-8 text (byte 0x{data[exc.start]:02x} at "
                f"offset {exc.start}; a binary file?)"
            ) from None
    if not data.strip():
        raise InputError(f"{source}: empty, not a JSON {what}")
    try:
        return json.loads(data, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as exc:
        raise InputError(
            f"{source}: not a JSON {what} ({exc.msg} at line {exc.lineno}, column {exc.colno})"
        ) from None
    except RecursionError:
        raise InputError(f"{source}: not a {what}: its JSON is nested too deeply") from None
    except InputError as exc:
        raise InputError(f"{source}: not a usable JSON {what}: {exc}") from None
