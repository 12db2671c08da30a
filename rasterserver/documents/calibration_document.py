"""The calibration (``rasterserver.calibration/1``): camera, projector, their raster and the
vertical, with the stereo-base check that needs both devices."""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import ConfigDict, Discriminator, Field, Strict, Tag, field_validator, model_validator

from rasterserver.documents.devices import CameraDocument, ProjectorDocument
from rasterserver.documents.fields import (
    GRAVITY_TOL,
    MIN_BASE_FRACTION,
    MIN_BASE_MM,
    Name,
    StrictDocument,
    Vector3,
    fmt,
    refuse,
    vec,
)
from rasterserver.documents.raster_document import RasterDocument


def _raster_tag(value: Any) -> str:
    return "document" if isinstance(value, dict) else "name"


class CalibrationDocument(StrictDocument):
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
                raise refuse(
                    f"must be a unit vector; its length is {fmt(norm)} (divide it by that)"
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
            MIN_BASE_MM, MIN_BASE_FRACTION * float(max(np.linalg.norm(cam), np.linalg.norm(proj)))
        )
        if across < needed:
            raise refuse(
                f"the camera and projector centres are {across:.3g} mm apart across the raster "
                f"lines (camera at {vec(cam)}, projector at {vec(proj)}); "
                f"triangulation needs a stereo base of at least {needed:.3g} mm",
                "projector.t",
            )
        return self
