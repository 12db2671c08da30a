"""What every field of the documents is built from: bounded finite numbers, vectors, names,
the strict base model, and the refusal that names a field.

The tolerances the checks use are here too, so that the models and their messages agree.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, Strict
from pydantic_core import PydanticCustomError

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

#: No quantity of a station comes near this (mm, px, units); beyond it arithmetic overflows.
MAX_MAGNITUDE = 1e12


def _bounded(value: float) -> float:
    if abs(value) > MAX_MAGNITUDE:
        raise refuse(f"{fmt(value)} is beyond ±{MAX_MAGNITUDE:g}")
    return value


#: A JSON number that is finite (NaN and infinities are refused) and not absurdly large; not a
#: string, not a boolean.
Finite = Annotated[float, Strict(), Field(allow_inf_nan=False), AfterValidator(_bounded)]
#: The same, greater than 0 (the bound before the validator keeps it in the JSON Schema).
Positive = Annotated[float, Strict(), Field(allow_inf_nan=False, gt=0), AfterValidator(_bounded)]
Vector3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Matrix3 = Annotated[list[Vector3], Field(min_length=3, max_length=3)]
Name = Annotated[str, Strict(), Field(min_length=1, max_length=200)]


def refuse(message: str, field: str | None = None) -> PydanticCustomError:
    """A validation error whose message is ``message`` as written, for ``field`` if given
    (a check of the whole model names the field it is about)."""
    # braces would be read as a template by pydantic-core
    text = message.replace("{", "(").replace("}", ")")
    return PydanticCustomError("document", text, {"field": field} if field else None)


def fmt(value: float) -> str:
    """``value`` as messages show it (six significant digits)."""
    return f"{value:.6g}"


def vec(values: Any) -> str:
    """A vector as messages show it, ``[1, 0, 0]``."""
    return "[" + ", ".join(fmt(float(v)) for v in values) + "]"


class StrictDocument(BaseModel):
    """Strict JSON: unknown fields are refused (a misspelt ``distorsion`` must not silently
    mean "no distortion")."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
