"""The back-shape analysis record: curvature, landmarks, body frame, lines and parameters.

One :class:`BackShape` is what the ``analysis`` stage makes of one smoothed
:class:`~rasterserver.records_surface.Surface`. Everything geometric is in the calibration's
world frame (mm; X to the patient's right, Y down along gravity, Z anterior, as the
reconstructed points), except where a field says it is in the body-fixed frame.

Landmarks are stored in the fixed order of :data:`LANDMARKS`; a landmark that was not found
is NaN, with a confidence of 0 and a reason in :attr:`BackShape.reasons`. Parameters are a
JSON object (name → value, unit, spread) because their set grows with the analysis; the
definitions and sign conventions are in ``docs/analysis.md``.
"""

from __future__ import annotations

import json
from typing import Any, ClassVar

import numpy as np

from rasterserver.errors import InputError
from rasterserver.records import Record

__all__ = ["LANDMARKS", "BackShape"]

LANDMARKS: tuple[str, ...] = ("VP", "DL", "DR", "DM", "SP")
"""Landmark order in :attr:`BackShape.landmarks`: vertebra prominens, left and right lumbar
dimple, their midpoint, sacrum point (top of the rima ani)."""


def _loads(owner: str, text: str, kind: type) -> Any:
    try:
        value = json.loads(text) if text else kind()
    except ValueError as exc:
        raise InputError(f"BackShape.{owner} is not valid JSON: {exc}") from None
    if not isinstance(value, kind):
        raise InputError(f"BackShape.{owner} must be a JSON {kind.__name__}")
    return value


class BackShape(Record):
    """Back-shape analysis of one surface.

    Attributes
    ----------
    x0, y0, spacing : float
        The surface grid the curvature maps lie on (as :class:`Surface`).
    mean_curvature, gaussian_curvature : numpy.ndarray
        ``(ny, nx)`` float32 maps H (1/mm) and K (1/mm²); NaN where not computed. H > 0 is
        convex towards the camera (a bump of the back), H < 0 concave (a dimple).
    landmarks : numpy.ndarray
        ``(5, 3)`` float64 world mm in the order of :data:`LANDMARKS`; NaN rows when not found.
    landmark_confidence : numpy.ndarray
        ``(5,)`` float64 in [0, 1]; 0 for a landmark not found.
    frame_origin : numpy.ndarray
        ``(3,)`` body-fixed frame origin (DM) in world mm; NaN when VP, DL or DR is missing.
    frame_axes : numpy.ndarray
        ``(3, 3)`` rows are the body frame's unit axes in world coordinates: transverse
        (towards the patient's right), vertical (up, DM → VP), sagittal (posterior,
        right-handed); NaN when the frame is missing.
    symmetry_line : numpy.ndarray
        ``(M, 3)`` world points of the symmetry line from VP down to DM (may be empty).
    surface_rotation : numpy.ndarray
        ``(M,)`` degrees along the symmetry line; positive turns the patient's right side
        posterior (as the simulator's axial rotation).
    midline : numpy.ndarray
        ``(M, 3)`` world points of the spinal midline (vertebral body centres).
    parameters : str
        JSON object ``{name: {"value": v, "unit": "mm"|"deg"|"1", "spread": s or null}}``.
    reasons : str
        JSON object ``{what: why}`` for every landmark, line or parameter not computed.
    reason : str
        Why the whole analysis is empty, or "".
    """

    kind: ClassVar[str] = "backshape"
    x0: float
    y0: float
    spacing: float
    mean_curvature: np.ndarray
    gaussian_curvature: np.ndarray
    landmarks: np.ndarray
    landmark_confidence: np.ndarray
    frame_origin: np.ndarray
    frame_axes: np.ndarray
    symmetry_line: np.ndarray
    surface_rotation: np.ndarray
    midline: np.ndarray
    parameters: str = "{}"
    reasons: str = "{}"
    reason: str = ""

    def validate(self) -> None:
        """Refuse arrays of the wrong shape or parameters that are not a JSON object."""
        if self.mean_curvature.shape != self.gaussian_curvature.shape:
            raise InputError("BackShape curvature maps differ in shape")
        if self.mean_curvature.ndim != 2:
            raise InputError("BackShape curvature maps must be 2-D")
        if self.landmarks.shape != (len(LANDMARKS), 3):
            raise InputError(f"BackShape.landmarks must be (5, 3), got {self.landmarks.shape}")
        if self.landmark_confidence.shape != (len(LANDMARKS),):
            raise InputError("BackShape.landmark_confidence must be (5,)")
        if self.frame_origin.shape != (3,) or self.frame_axes.shape != (3, 3):
            raise InputError("BackShape frame must be an origin (3,) and axes (3, 3)")
        m = self.symmetry_line.shape[0] if self.symmetry_line.ndim == 2 else -1
        if self.symmetry_line.shape != (m, 3) or self.midline.shape != (m, 3):
            raise InputError("BackShape.symmetry_line and midline must both be (M, 3)")
        if self.surface_rotation.shape != (m,):
            raise InputError("BackShape.surface_rotation must be (M,)")
        _loads("parameters", self.parameters, dict)
        _loads("reasons", self.reasons, dict)

    def landmark(self, name: str) -> np.ndarray | None:
        """The world position of landmark ``name`` (one of :data:`LANDMARKS`), None if absent."""
        try:
            point = self.landmarks[LANDMARKS.index(name)]
        except ValueError:
            raise InputError(f"no landmark {name!r}; landmarks: {', '.join(LANDMARKS)}") from None
        return None if not np.all(np.isfinite(point)) else np.array(point)

    def parameter_table(self) -> dict[str, dict[str, Any]]:
        """The parameters as ``{name: {"value", "unit", "spread"}}``."""
        return _loads("parameters", self.parameters, dict)

    def reason_table(self) -> dict[str, str]:
        """What could not be computed, and why."""
        return _loads("reasons", self.reasons, dict)

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary: landmarks (world mm or None), parameters, reasons."""
        return {
            "landmarks": {
                name: (None if (p := self.landmark(name)) is None else [float(v) for v in p])
                for name in LANDMARKS
            },
            "landmark_confidence": {
                name: float(c) for name, c in zip(LANDMARKS, self.landmark_confidence, strict=True)
            },
            "parameters": self.parameter_table(),
            "reasons": self.reason_table(),
            "reason": self.reason,
        }

    @classmethod
    def empty(cls, reason: str, *, reasons: dict[str, str] | None = None) -> BackShape:
        """An analysis with nothing found, saying ``reason``."""
        nan3 = np.full(3, np.nan)
        return cls(
            x0=0.0,
            y0=0.0,
            spacing=1.0,
            mean_curvature=np.zeros((0, 0), dtype=np.float32),
            gaussian_curvature=np.zeros((0, 0), dtype=np.float32),
            landmarks=np.full((len(LANDMARKS), 3), np.nan),
            landmark_confidence=np.zeros(len(LANDMARKS)),
            frame_origin=nan3,
            frame_axes=np.full((3, 3), np.nan),
            symmetry_line=np.zeros((0, 3)),
            surface_rotation=np.zeros(0),
            midline=np.zeros((0, 3)),
            parameters="{}",
            reasons=json.dumps(reasons or {}, sort_keys=True),
            reason=reason,
        )
