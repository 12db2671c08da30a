"""The calibration and raster definition documents: read and validated here, and only here.

A calibration (``rasterserver.calibration/1``) and a raster definition
(``rasterserver.raster/1``) reach the server as files on the command line, as JSON bodies of
the HTTP API, and as rows of the catalogue. Every one of those readers goes through this
module, so a document is accepted or refused for the same reasons everywhere:

:func:`read_document`
    JSON text (a file, bytes or a string) to a Python value, with a sentence instead of a
    traceback for a missing file, a directory, binary or non-UTF-8 bytes, bad JSON, JSON
    nested too deeply, duplicate keys or a file too large to be a document.
:func:`calibration_from_document`, :func:`raster_from_document`
    A parsed document to a :class:`~rasterserver.optics.Station` or a
    :class:`~rasterserver.raster.Raster`, validated by the typed models below.
:func:`load_calibration_document`, :func:`load_raster_document`
    Both steps.

The models (:class:`CalibrationDocument`, :class:`RasterDocument` and their parts) are the
format's definition: their JSON Schema is published in the OpenAPI document and the field
tables of ``docs/formats.md`` are generated from it (:func:`format_tables`). Besides types
and required fields they check what makes a document usable: finite numbers only, ``K`` upper
triangular with positive focal lengths and last row ``[0, 0, 1]``, ``R`` a rotation (within
:data:`ROTATION_TOL`), positive image sizes, distortion coefficients OpenCV can hold and a lens
model that does not fold back inside the image, camera and projector centres apart across the
raster lines, a raster whose lines increase and whose code identifies positions as declared.

Every refusal is an :class:`~rasterserver.errors.InputError` naming the source and the field,
e.g. ``cal.json: camera.K: focal lengths must be positive (fx = 0, fy = 0)``.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Strict,
    Tag,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from rasterserver.errors import InputError
from rasterserver.optics import CALIBRATION_FORMAT, Camera, PinholeDevice, Projector, Station
from rasterserver.raster import RASTER_FORMAT, Raster, closest_windows

__all__ = [
    "CALIBRATION_FORMAT",
    "GRAVITY_TOL",
    "MAX_DOCUMENT_BYTES",
    "MAX_MAGNITUDE",
    "RASTER_FORMAT",
    "ROTATION_TOL",
    "CalibrationDocument",
    "CameraDocument",
    "ProjectorDocument",
    "RasterCode",
    "RasterDocument",
    "RasterLine",
    "calibration_from_document",
    "device_from_document",
    "fill_format_tables",
    "format_tables",
    "load_calibration_document",
    "load_raster_document",
    "raster_from_document",
    "read_document",
    "validate_calibration",
    "validate_raster",
]

#: A calibration is a few kilobytes, with an inline raster some tens: anything this large is
#: not one (and is not read into memory whole to find that out).
MAX_DOCUMENT_BYTES = 4 * 1024 * 1024
#: ``R @ R.T`` may differ from the identity by this much (rounded decimals in a hand-made
#: document); the rotation used is the nearest proper one.
ROTATION_TOL = 1e-6
#: How far from 1 the length of ``gravity`` may be.
GRAVITY_TOL = 1e-6
#: The stereo base across the raster lines must be at least this (mm) ...
MIN_BASE_MM = 1.0
#: ... and at least this fraction of the devices' distance from the world origin (the origin
#: lies on the nominal back plane): 1 % is a triangulation angle of about 0.6 degrees.
MIN_BASE_FRACTION = 0.01
#: At most this many problems are listed in one message.
_MAX_LISTED = 5

#: What each known ``format`` tag is, for a document given where another is expected.
_KNOWN_FORMATS = {
    CALIBRATION_FORMAT: "a calibration",
    RASTER_FORMAT: "a raster definition",
    "rasterserver.control_points/1": "a control-point file",
    "rasterserver.ground-truth/1": "a simulator ground truth",
}

# --- field types ---------------------------------------------------------------------------

#: No quantity of a station comes near this (mm, px, units); beyond it arithmetic overflows.
MAX_MAGNITUDE = 1e12


def _bounded(value: float) -> float:
    if abs(value) > MAX_MAGNITUDE:
        raise _refuse(f"{_fmt(value)} is beyond ±{MAX_MAGNITUDE:g}")
    return value


#: A JSON number that is finite (NaN and infinities are refused) and not absurdly large; not a
#: string, not a boolean.
Finite = Annotated[float, Strict(), Field(allow_inf_nan=False), AfterValidator(_bounded)]
#: The same, greater than 0 (the bound before the validator keeps it in the JSON Schema).
Positive = Annotated[float, Strict(), Field(allow_inf_nan=False, gt=0), AfterValidator(_bounded)]
Vector3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Matrix3 = Annotated[list[Vector3], Field(min_length=3, max_length=3)]
Name = Annotated[str, Strict(), Field(min_length=1, max_length=200)]


def _refuse(message: str, field: str | None = None) -> PydanticCustomError:
    """A validation error whose message is ``message`` as written, for ``field`` if given
    (a check of the whole model names the field it is about)."""
    # braces would be read as a template by pydantic-core
    text = message.replace("{", "(").replace("}", ")")
    return PydanticCustomError("document", text, {"field": field} if field else None)


def _fmt(value: float) -> str:
    return f"{value:.6g}"


def _vec(values: Any) -> str:
    return "[" + ", ".join(_fmt(float(v)) for v in values) + "]"


class _Document(BaseModel):
    """Strict JSON: unknown fields are refused (a misspelt ``distorsion`` must not silently
    mean "no distortion")."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# --- devices -------------------------------------------------------------------------------


class _DeviceDocument(_Document):
    """What camera and projector share: the OpenCV pinhole model with distortion and pose."""

    model: Literal["opencv-pinhole"] = Field(
        "opencv-pinhole", description="the device model; `opencv-pinhole` is the only one so far"
    )
    K: Matrix3 = Field(
        description="intrinsic matrix `[[fx, s, cx], [0, fy, cy], [0, 0, 1]]` in pixels "
        "(camera) or diapositive units (projector); fx, fy > 0 (checked)"
    )
    distortion: Annotated[list[Finite], Field(min_length=4, max_length=14)] = Field(
        [0.0] * 5,
        description="`[k1, k2, p1, p2, k3]`, OpenCV order, acting on normalised coordinates; "
        "4 values (k3 = 0) or OpenCV's 8, 12 or 14 with the terms after k3 zero are accepted; "
        "the lens model must not fold back inside the image (checked)",
    )
    R: Matrix3 = Field(
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        description="rotation world → device: orthonormal with determinant +1 (checked to "
        "1e-6; the nearest rotation is used)",
    )
    t: Vector3 = Field(description="translation world → device, mm: `p_dev = R @ p_world + t`")
    centre: Vector3 | None = Field(
        None,
        description="projection centre in world mm, `-R.T @ t`; written for readers' "
        "convenience, derived when reading (a value that disagrees by over 0.01 mm is refused)",
    )

    @field_validator("K")
    @classmethod
    def _intrinsics(cls, k: list[list[float]]) -> list[list[float]]:
        problems = []
        if not (k[0][0] > 0 and k[1][1] > 0):
            problems.append(
                f"focal lengths must be positive (fx = {_fmt(k[0][0])}, fy = {_fmt(k[1][1])})"
            )
        if any(abs(v) > 1e-9 for v in (k[1][0], k[2][0], k[2][1])) or abs(k[2][2] - 1) > 1e-9:
            problems.append(
                "must be upper triangular with last row [0, 0, 1] "
                f"(rows 2 and 3 are {_vec(k[1])}, {_vec(k[2])})"
            )
        if problems:
            raise _refuse("; ".join(problems))
        return k

    @field_validator("distortion")
    @classmethod
    def _distortion_terms(cls, dist: list[float]) -> list[float]:
        if len(dist) not in (4, 5, 8, 12, 14):
            raise _refuse(
                f"{len(dist)} coefficients; OpenCV uses 4, 5, 8, 12 or 14 "
                "(k1, k2, p1, p2[, k3[, ...]])"
            )
        if any(dist[5:]):
            raise _refuse(
                f"only k1, k2, p1, p2, k3 are modelled; coefficients 6 to {len(dist)} must be 0"
            )
        return dist

    @field_validator("R")
    @classmethod
    def _rotation(cls, r: list[list[float]]) -> list[list[float]]:
        rot = np.asarray(r, dtype=np.float64)
        error = float(np.abs(rot @ rot.T - np.eye(3)).max())
        if error > ROTATION_TOL:
            raise _refuse(
                f"not a rotation: R @ R.T differs from the identity by {error:.3g} "
                f"(tolerance {ROTATION_TOL:g})"
            )
        if np.linalg.det(rot) < 0:
            raise _refuse("a reflection (determinant -1), not a rotation")
        return r

    @model_validator(mode="after")
    def _centre_and_lens(self) -> _DeviceDocument:
        if self.centre is not None:
            derived = self.position()
            off = float(np.linalg.norm(np.asarray(self.centre) - derived))
            if off > 0.01:
                raise _refuse(
                    f"{_vec(self.centre)} is not -R.T @ t = {_vec(derived)} (off by "
                    f"{off:.3g} mm); it is derived: correct or remove it",
                    "centre",
                )
        self._check_lens()
        return self

    def rotation(self) -> np.ndarray:
        """``R``, or the nearest proper rotation to it when it is off by more than the devices
        accept (1e-9: a document with rounded decimals)."""
        rot = np.asarray(self.R, dtype=np.float64)
        if np.abs(rot @ rot.T - np.eye(3)).max() <= 1e-9:
            return rot  # exactly as written, so a document round-trips bit for bit
        u, _, vt = np.linalg.svd(rot)
        return u @ vt

    def position(self) -> np.ndarray:
        """The projection centre in world mm, ``-R.T @ t``."""
        return -self.rotation().T @ np.asarray(self.t, dtype=np.float64)

    def coefficients(self) -> np.ndarray:
        """The five coefficients ``(k1, k2, p1, p2, k3)`` of the model."""
        dist = np.zeros(5)
        dist[: min(5, len(self.distortion))] = self.distortion[:5]
        return dist

    def _check_lens(self) -> None:
        """Refuse a radial distortion that folds back inside the image: it has no inverse
        there (``undistort_normalized`` would converge to the wrong branch or not at all)."""
        k1, k2, _, _, k3 = self.coefficients()
        if not (k1 or k2 or k3):
            return
        w, h = float(self.width), float(self.height)  # type: ignore[attr-defined]
        k = np.asarray(self.K, dtype=np.float64)
        corners_u = np.array([-0.5, w - 0.5, -0.5, w - 0.5])
        corners_v = np.array([-0.5, -0.5, h - 0.5, h - 0.5])
        yd = (corners_v - k[1, 2]) / k[1, 1]
        xd = (corners_u - k[0, 2] - k[0, 1] * yd) / k[0, 0]
        reach = float(np.hypot(xd, yd).max())  # distorted radius of the farthest corner
        r = np.linspace(0.0, 4.0 * reach, 4001)
        r2 = r * r
        distorted = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        slope = 1 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3))
        folds = np.flatnonzero(slope <= 0)
        end = folds[0] if folds.size else r.size - 1
        if distorted[: end + 1].max() < reach:
            where = f"folds back at {r[end]:.3g}" if folds.size else "never reaches"
            raise _refuse(
                f"the radial model {where} (normalised radius) inside the image, which "
                f"reaches {reach:.3g}: not invertible there",
                "distortion",
            )


class CameraDocument(_DeviceDocument):
    """The recording camera, in pixels."""

    model_config = ConfigDict(title="camera")

    width: Annotated[int, Strict(), Field(ge=1, le=100_000)] = Field(
        description="image columns (an integer ≥ 1); a frame must have exactly this size"
    )
    height: Annotated[int, Strict(), Field(ge=1, le=100_000)] = Field(
        description="image rows (an integer ≥ 1)"
    )


class ProjectorDocument(_DeviceDocument):
    """The raster projector, an inverse camera, in diapositive units."""

    model_config = ConfigDict(title="projector")

    width: Positive = Field(
        description="extent of the usable diapositive area (units, > 0): valid coordinates "
        "lie in `[-0.5, width - 0.5]`; the renderer sends no light outside it"
    )
    height: Positive = Field(
        description="extent of the usable diapositive area along `v` (units, > 0)"
    )


# --- raster definition ---------------------------------------------------------------------


class RasterCode(_Document):
    """How the line kinds identify positions."""

    model_config = ConfigDict(title="code")

    window: Annotated[int, Strict(), Field(ge=1)] = Field(
        description="code window length k: the kinds of any k consecutive lines identify their "
        "absolute position (checked against the lines)"
    )
    min_distance: Annotated[int, Strict(), Field(ge=1)] = Field(
        1,
        description="minimum Hamming distance between any two windows (1: unique; 2: a single "
        "misread kind is detected, never mistaken for another position); checked",
    )


class RasterLine(_Document):
    """One line of the diapositive."""

    model_config = ConfigDict(title="line")

    number: Annotated[int, Strict(), Field(ge=-(2**31), le=2**31 - 1)] = Field(
        description="absolute line number (what the line numbering stage must recover); unique"
    )
    v: Finite = Field(description="diapositive coordinate of the line centre; strictly increasing")
    kind: Literal["light", "heavy"] = Field(description="`light` or `heavy`")
    width: Positive = Field(
        description="full width of the transparent stripe in diapositive units (> 0), before "
        "projector defocus"
    )


class RasterDocument(_Document):
    """A raster diapositive: its lines in order of increasing ``v`` and their code."""

    model_config = ConfigDict(title="raster definition")

    format: Literal["rasterserver.raster/1"] = Field(description="the format tag (required)")
    name: Annotated[str, Strict(), Field(min_length=1, max_length=100)] = Field(
        description="identifier; `default` is the built-in diapositive"
    )
    description: Annotated[str, Strict(), Field(max_length=10_000)] = Field(
        "", description="free text"
    )
    units: Annotated[str, Strict(), Field(max_length=200)] | None = Field(
        None,
        description="informational: positions and widths are diapositive units (the "
        "projector's `v`)",
    )
    code: RasterCode = Field(description="the code of the line kinds")
    lines: Annotated[list[RasterLine], Field(min_length=1, max_length=10_000)] = Field(
        description="one object per line, **in order of increasing `v`** (top of the back to "
        "bottom)"
    )

    @model_validator(mode="after")
    def _lines_and_code(self) -> RasterDocument:
        v = np.array([ln.v for ln in self.lines])
        if v.size > 1 and np.any(np.diff(v) <= 0):
            i = int(np.flatnonzero(np.diff(v) <= 0)[0]) + 1
            raise _refuse(
                f"{_fmt(v[i])} does not exceed the previous line's {_fmt(v[i - 1])}: lines "
                "are listed in order of strictly increasing v",
                f"lines[{i}].v",
            )
        seen: dict[int, int] = {}
        for i, ln in enumerate(self.lines):
            if ln.number in seen:
                raise _refuse(
                    f"{ln.number} is also the number of lines[{seen[ln.number]}]",
                    f"lines[{i}].number",
                )
            seen[ln.number] = i
        window, wanted = self.code.window, self.code.min_distance
        if window > len(self.lines):
            raise _refuse(
                f"{window} is longer than the raster ({len(self.lines)} lines)", "code.window"
            )
        if wanted > window:
            raise _refuse(f"{wanted} exceeds the window ({window})", "code.min_distance")
        bits = np.array([ln.kind == "heavy" for ln in self.lines], dtype=np.uint8)
        distance, i, j = closest_windows(bits, window)
        if distance < wanted:
            how = "are identical" if distance == 0 else f"differ in only {distance} line(s)"
            raise _refuse(
                f"the windows of {window} lines starting at lines[{i}] and lines[{j}] {how}, "
                f"but min_distance is {wanted}: the kinds do not identify positions as "
                "declared",
                "code",
            )
        return self


# --- calibration ---------------------------------------------------------------------------


def _raster_tag(value: Any) -> str:
    return "document" if isinstance(value, dict) else "name"


class CalibrationDocument(_Document):
    """A calibrated station: camera, projector, the raster they use, and the vertical."""

    model_config = ConfigDict(title="calibration")

    format: Literal["rasterserver.calibration/1"] = Field(description="the format tag (required)")
    name: Name = Field("default", description="station / calibration label")
    units: Literal["mm"] = Field("mm", description="`mm`: world coordinates are millimetres")
    conventions: Annotated[str, Strict(), Field(max_length=2000)] = Field(
        "", description="one-line reminder of the conventions (informational)"
    )
    camera: CameraDocument = Field(description="the recording camera, in pixels")
    projector: ProjectorDocument = Field(description="the raster projector, in diapositive units")
    raster: Annotated[
        Annotated[Annotated[str, Strict(), Field(min_length=1, max_length=100)], Tag("name")]
        | Annotated[RasterDocument, Tag("document")],
        Discriminator(_raster_tag),
    ] = Field(
        "default",
        description="name of a raster definition (built in, like `default`, or stored and "
        "named when the calibration is stored) or a full `rasterserver.raster/1` document "
        "inline",
    )
    gravity: Vector3 | None = Field(
        None,
        description="direction of gravity (down) in the world frame, a unit vector (length "
        "1 within 1e-6): `[0, 1, 0]` when the world's Y axis is plumb, as for a calibration "
        "from the control-point body; absent: unknown (the back-shape analysis refuses it)",
    )

    @field_validator("gravity")
    @classmethod
    def _unit_gravity(cls, g: list[float] | None) -> list[float] | None:
        if g is not None:
            norm = math.sqrt(sum(c * c for c in g))
            if abs(norm - 1.0) > GRAVITY_TOL:
                raise _refuse(
                    f"must be a unit vector; its length is {_fmt(norm)} (divide it by that)"
                )
        return g

    @model_validator(mode="after")
    def _stereo_base(self) -> CalibrationDocument:
        # Every light plane contains the line through the projector centre along its x axis
        # (the direction of the raster lines); a camera centre on or near that line sees each
        # plane edge-on and nothing can be triangulated.
        cam, proj = self.camera.position(), self.projector.position()
        along = self.projector.rotation()[0]
        base = proj - cam
        across = float(np.linalg.norm(base - (base @ along) * along))
        needed = max(
            MIN_BASE_MM, MIN_BASE_FRACTION * max(np.linalg.norm(cam), np.linalg.norm(proj))
        )
        if across < needed:
            raise _refuse(
                f"the camera and projector centres are {across:.3g} mm apart across the raster "
                f"lines (camera at {_vec(cam)}, projector at {_vec(proj)}); "
                f"triangulation needs a stereo base of at least {needed:.3g} mm",
                "projector.t",
            )
        return self


# --- reading -------------------------------------------------------------------------------


def _json_kind(value: Any) -> str:
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


def _check_kind(document: Any, fmt: str, what: str, source: str) -> dict[str, Any]:
    """Refuse anything but an object tagged ``fmt``, saying what it is instead."""
    if not isinstance(document, dict):
        raise InputError(
            f"{source}: a {what} is a JSON object ({{...}}), this is {_json_kind(document)}"
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
    shown = given if isinstance(given, str) and len(given) <= 100 else _json_kind(given)
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


def _refusal(source: str, exc: ValidationError) -> InputError:
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
        raise _refusal(source, exc) from None
    except RecursionError:
        raise InputError(f"{source}: nested too deeply to be a {what}") from None


def _device(cls: type[PinholeDevice], doc: _DeviceDocument) -> PinholeDevice:
    return cls(
        K=np.asarray(doc.K, dtype=np.float64),
        dist=doc.coefficients(),
        R=doc.rotation(),
        t=np.asarray(doc.t, dtype=np.float64),
        width=doc.width,  # type: ignore[attr-defined]
        height=doc.height,  # type: ignore[attr-defined]
    )


def _raster(doc: RasterDocument) -> Raster:
    return Raster(
        name=doc.name,
        numbers=np.array([ln.number for ln in doc.lines], dtype=np.int64),
        positions=np.array([ln.v for ln in doc.lines], dtype=np.float64),
        kinds=tuple(ln.kind for ln in doc.lines),
        widths=np.array([ln.width for ln in doc.lines], dtype=np.float64),
        window=doc.code.window,
        min_distance=doc.code.min_distance,
        description=doc.description,
    )


def device_from_document(cls: type[PinholeDevice], document: Any, *, source: str) -> PinholeDevice:
    """A camera or projector from its part of a calibration document (``cls`` says which).

    Raises
    ------
    InputError
        The device description is refused.
    """
    model = CameraDocument if issubclass(cls, Camera) else ProjectorDocument
    try:
        doc = model.model_validate(document)
    except ValidationError as exc:
        raise _refusal(source, exc) from None
    return _device(cls, doc)


def calibration_from_document(document: Any, *, source: str = "calibration") -> Station:
    """The station a parsed calibration document describes, after every check.

    Parameters
    ----------
    document : Any
        The parsed JSON (``rasterserver.calibration/1``).
    source : str
        How messages name it (a file name, ``calibration clinic-1:2``).

    Returns
    -------
    Station

    Raises
    ------
    InputError
        Not an object, another kind of document, or a refused field.
    """
    doc = validate_calibration(document, source=source)
    raster = doc.raster if isinstance(doc.raster, str) else _raster(doc.raster)
    return Station(
        camera=_device(Camera, doc.camera),  # type: ignore[arg-type]
        projector=_device(Projector, doc.projector),  # type: ignore[arg-type]
        raster=raster,
        name=doc.name,
        gravity=None if doc.gravity is None else np.asarray(doc.gravity, dtype=np.float64),
    )


def raster_from_document(document: Any, *, source: str = "raster definition") -> Raster:
    """The raster a parsed ``rasterserver.raster/1`` document describes, after every check.

    Raises
    ------
    InputError
        Not an object, another kind of document, or a refused field.
    """
    return _raster(validate_raster(document, source=source))


def load_calibration_document(data: str | bytes | Path, *, source: str | None = None) -> Station:
    """Read and check a calibration: a file, its bytes or its JSON text.

    Parameters
    ----------
    data : str, bytes or Path
        The calibration (a ``str`` is JSON text, not a path).
    source : str, optional
        How messages name it; the file's name by default.

    Returns
    -------
    Station

    Raises
    ------
    InputError
        Unreadable, not JSON, or refused (see :func:`read_document`,
        :func:`calibration_from_document`).
    """
    name = source or (data.name if isinstance(data, Path) else "calibration")
    return calibration_from_document(
        read_document(data, what="calibration", source=name), source=name
    )


def load_raster_document(data: str | bytes | Path, *, source: str | None = None) -> Raster:
    """Read and check a raster definition: a file, its bytes or its JSON text.

    Raises
    ------
    InputError
        Unreadable, not JSON, or refused.
    """
    name = source or (data.name if isinstance(data, Path) else "raster definition")
    return raster_from_document(
        read_document(data, what="raster definition", source=name), source=name
    )


# --- documentation -------------------------------------------------------------------------


def _type_text(schema: dict[str, Any], defs: dict[str, Any]) -> str:
    if "$ref" in schema:
        return defs[schema["$ref"].rsplit("/", 1)[-1]].get("title", "object")
    if "const" in schema:
        return f'`"{schema["const"]}"`'
    if "enum" in schema:
        return " or ".join(f'`"{v}"`' for v in schema["enum"])
    if "anyOf" in schema or "oneOf" in schema:
        options = schema.get("anyOf") or schema["oneOf"]
        shown = [_type_text(o, defs) for o in options if o.get("type") != "null"]
        nullable = any(o.get("type") == "null" for o in options)
        return " or ".join(shown) + (" (or null)" if nullable else "")
    kind = schema.get("type")
    if kind == "array":
        items = schema.get("items", {})
        n = schema.get("minItems")
        fixed = n is not None and n == schema.get("maxItems")
        inner = _type_text(items, defs)
        if items.get("type") == "array" and fixed:
            m = items.get("minItems")
            return f"{n}×{m} numbers" if items.get("items", {}).get("type") == "number" else inner
        if fixed and items.get("type") == "number":
            return f"{n} numbers"
        if items.get("type") == "number":
            return f"{n}–{schema.get('maxItems')} numbers"
        return f"array of {inner}"
    if "minimum" in schema and "maximum" in schema:
        return f"{kind}, {schema['minimum']} to {schema['maximum']}"
    bounds = []
    for key, sign in (("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤")):
        if key in schema:
            bounds.append(f"{sign} {schema[key]}")
    return " ".join([str(kind), *bounds]) if kind else "any"


def _table(schema: dict[str, Any], defs: dict[str, Any]) -> list[str]:
    rows = ["| field | type | required | meaning |", "|---|---|---|---|"]
    required = set(schema.get("required", ()))
    for name, prop in schema["properties"].items():
        if name in required:
            need = "yes"
        elif "default" in prop and prop["default"] is not None:
            need = f"no (`{json.dumps(prop['default'])}`)"
        else:
            need = "no"
        if len(need) > 30:  # long defaults (a 3×3 identity) in words
            need = "no (identity)" if name == "R" else "no (zeros)"
        text = prop.get("description", "").replace("|", "\\|")
        rows.append(f"| `{name}` | {_type_text(prop, defs)} | {need} | {text} |")
    return rows


def format_tables() -> dict[str, str]:
    """Markdown field tables of both documents, generated from the models' JSON Schema.

    ``docs/formats.md`` holds them between ``<!-- generated: KEY -->`` and
    ``<!-- end generated -->`` markers; a test fails when they differ from the models.

    Returns
    -------
    dict
        ``{"calibration": ..., "device": ..., "raster": ..., "raster-code": ...,
        "raster-line": ...}``, each a table (no trailing newline).
    """
    calibration = CalibrationDocument.model_json_schema()
    raster = RasterDocument.model_json_schema()
    cdefs, rdefs = calibration["$defs"], raster["$defs"]
    camera, projector = cdefs["CameraDocument"], cdefs["ProjectorDocument"]
    # one device table: the fields both share, with the camera's and projector's sizes
    shared = dict(camera["properties"])
    sizes = {
        side: {
            "type": "camera: integer ≥ 1; projector: number > 0",
            "description": f"camera: {shared.pop(side)['description']}; projector: "
            f"{projector['properties'][side]['description']}",
        }
        for side in ("width", "height")
    }
    model = {"model": shared.pop("model")}
    device = {"properties": model | sizes | shared, "required": camera["required"]}
    return {
        "calibration": "\n".join(_table(calibration, cdefs)),
        "device": "\n".join(_table(device, cdefs)),
        "raster": "\n".join(_table(raster, rdefs)),
        "raster-code": "\n".join(_table(rdefs["RasterCode"], rdefs)),
        "raster-line": "\n".join(_table(rdefs["RasterLine"], rdefs)),
    }


_GENERATED = re.compile(
    r"(<!-- generated from rasterserver\.documents\.format_tables\(\): ([a-z-]+) -->\n)"
    r".*?(<!-- end generated -->)",
    re.S,
)


def fill_format_tables(markdown: str) -> str:
    """``markdown`` with every generated block replaced by the current :func:`format_tables`.

    A block is ``<!-- generated from rasterserver.documents.format_tables(): KEY -->``, the
    table, ``<!-- end generated -->``; text outside the blocks is kept as it is.
    """
    tables = format_tables()
    return _GENERATED.sub(lambda m: f"{m[1]}{tables[m[2]]}\n{m[3]}", markdown)
