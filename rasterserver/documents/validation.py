"""A parsed document checked against its model; refusals worded for people, naming the source
and the field (``cal.json: camera.K: focal lengths must be positive``)."""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from rasterserver.documents.calibration_document import CalibrationDocument
from rasterserver.documents.raster_document import RasterDocument
from rasterserver.documents.reading import json_kind
from rasterserver.errors import InputError
from rasterserver.optics import CALIBRATION_FORMAT
from rasterserver.raster import RASTER_FORMAT

#: At most this many problems are listed in one message.
_MAX_LISTED = 5

#: What each known ``format`` tag is, for a document given where another is expected.
_KNOWN_FORMATS = {
    CALIBRATION_FORMAT: "a calibration",
    RASTER_FORMAT: "a raster definition",
    "rasterserver.control_points/1": "a control-point file",
    "rasterserver.ground-truth/1": "a simulator ground truth",
}


def _check_kind(document: Any, fmt: str, what: str, source: str) -> dict[str, Any]:
    """Refuse anything but an object tagged ``fmt``, saying what it is instead."""
    if not isinstance(document, dict):
        raise InputError(
            f"{source}: a {what} is a JSON object ({{...}}), this is {json_kind(document)}"
        )
    given = document.get("format")
    if given == fmt:
        return document
    if isinstance(given, str) and given in _KNOWN_FORMATS:
        raise InputError(
            f"{source}: this is {_KNOWN_FORMATS[given]} ({given}), not a {what} ({fmt})"
        )
    if given is None:
        hint = ""
        if "camera" in document or "projector" in document:
            hint = ", but it looks like a calibration"
        elif "lines" in document:
            hint = ", but it looks like a raster definition"
        raise InputError(f'{source}: format: missing{hint}; a {what} begins with "format": "{fmt}"')
    shown = given if isinstance(given, str) and len(given) <= 100 else json_kind(given)
    raise InputError(f"{source}: format: {shown!r} is not {fmt}; this is not a {what}")


def _location(error: Any) -> str:
    """``camera.K``, ``lines[3].v``: where a validation error is, without union tags."""
    parts: list[str | int] = []
    for p in error["loc"]:
        if p in ("name", "document") and parts and parts[-1] == "raster":
            continue  # the tag of the raster union, not a field
        parts.append(p)
    field = (error.get("ctx") or {}).get("field")
    text = ""
    for p in parts:
        text += f"[{p}]" if isinstance(p, int) else (f".{p}" if text else str(p))
    if field:
        text = f"{text}.{field}" if text else field
    return text


_MESSAGES = {
    "missing": "missing (required)",
    "extra_forbidden": "unknown field (misspelt?)",
    "finite_number": "must be a finite number (NaN and infinities are refused)",
    "float_type": "must be a number",
    "int_type": "must be an integer",
    "string_type": "must be a string",
    "list_type": "must be an array",
    "model_type": "must be an object",
    "model_attributes_type": "must be an object",
}


def _problem(error: Any) -> str:
    message = _MESSAGES.get(error["type"], error["msg"])
    # pydantic's "Input should be greater than 0" reads "must be greater than 0" after a field
    for theirs, ours in (
        ("Input should be", "must be"),
        ("List should have", "must have"),
        ("String should have", "must have"),
        (" after validation", ""),
    ):
        message = message.replace(theirs, ours)
    where = _location(error)
    return f"{where}: {message}" if where else message


def refusal(source: str, exc: ValidationError) -> InputError:
    """One :class:`InputError` for a validation error: the source, then each problem."""
    errors = exc.errors(include_url=False, include_input=False)
    listed = [_problem(e) for e in errors[:_MAX_LISTED]]
    more = f" (and {len(errors) - _MAX_LISTED} more)" if len(errors) > _MAX_LISTED else ""
    return InputError(f"{source}: " + "; ".join(listed) + more)


def validate_calibration(document: Any, *, source: str = "calibration") -> CalibrationDocument:
    """Check a parsed calibration document; return its model.

    Raises
    ------
    InputError
        Naming ``source`` and every refused field (at most five).
    """
    return _validate(CalibrationDocument, document, CALIBRATION_FORMAT, "calibration", source)


def validate_raster(document: Any, *, source: str = "raster definition") -> RasterDocument:
    """Check a parsed raster definition; return its model.

    Raises
    ------
    InputError
        Naming ``source`` and every refused field (at most five).
    """
    return _validate(RasterDocument, document, RASTER_FORMAT, "raster definition", source)


_Model = TypeVar("_Model", bound=BaseModel)


def _validate(model: type[_Model], document: Any, fmt: str, what: str, source: str) -> _Model:
    checked = _check_kind(document, fmt, what, source)
    try:
        return model.model_validate(checked)
    except ValidationError as exc:
        raise refusal(source, exc) from None
    except RecursionError:
        raise InputError(f"{source}: nested too deeply to be a {what}") from None
