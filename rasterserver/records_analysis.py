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

__all__ = ["FRAME_LANDMARKS", "LANDMARKS", "SAGITTAL_POINTS", "BackShape", "combine", "landmark_in"]

LANDMARKS: tuple[str, ...] = ("VP", "DL", "DR", "DM", "SP")
"""Landmark order in :attr:`BackShape.landmarks`: vertebra prominens, left and right lumbar
dimple, their midpoint, sacrum point (top of the rima ani)."""

FRAME_LANDMARKS: tuple[str, ...] = LANDMARKS[:4]
"""The landmarks the body-fixed frame is built from (origin DM, axes from VP, DL → DR)."""

SAGITTAL_POINTS: tuple[str, ...] = ("ICT", "KA", "ITL", "LA", "ILS")
"""Order in :attr:`BackShape.sagittal_points`: the inflection points of the symmetry line's
sagittal profile (cervico-thoracic, thoraco-lumbar, lumbo-sacral) and the kyphosis and
lordosis apices."""


def _loads(owner: str, text: str, kind: type) -> Any:
    try:
        value = json.loads(text) if text else kind()
    except ValueError as exc:
        raise InputError(f"BackShape.{owner} is not valid JSON: {exc}") from None
    if not isinstance(value, kind):
        raise InputError(f"BackShape.{owner} must be a JSON {kind.__name__}")
    return value


def landmark_in(table: np.ndarray, name: str) -> np.ndarray | None:
    """Landmark ``name``'s row of a ``(len(LANDMARKS), 3)`` table, None when not found (NaN).

    Raises
    ------
    InputError
        ``name`` is not one of :data:`LANDMARKS`.
    """
    try:
        point = table[LANDMARKS.index(name)]
    except ValueError:
        raise InputError(f"no landmark {name!r}; landmarks: {', '.join(LANDMARKS)}") from None
    return None if not np.all(np.isfinite(point)) else np.array(point)


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
    max_curvature, min_curvature : numpy.ndarray or None
        ``(ny, nx)`` float32 principal curvature maps κ1 ≥ κ2 (1/mm), on the grid of the
        curvature maps.
    principal_direction : numpy.ndarray or None
        ``(ny, nx)`` float32 angle (radians, in (-π/2, π/2]) of the κ1 direction projected
        onto the grid plane, from the grid's x axis towards its y axis.
    sagittal_points : numpy.ndarray or None
        ``(5, 3)`` world mm of the sagittal profile's points in the order of
        :data:`SAGITTAL_POINTS`; NaN rows when not found.
    level_axes : numpy.ndarray or None
        ``(3, 3)`` rows are the axes of the grid the curvature maps lie on (the *level
        frame*: x to the patient's right, y along gravity, z the horizontal camera axis) in
        world coordinates; the identity when gravity is the world's +Y. Cell ``[i, j]`` of a
        map is the level point ``(x0 + j * spacing, y0 + i * spacing)``.
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
    max_curvature: np.ndarray | None = None
    min_curvature: np.ndarray | None = None
    principal_direction: np.ndarray | None = None
    sagittal_points: np.ndarray | None = None
    level_axes: np.ndarray | None = None

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
        for name in ("max_curvature", "min_curvature", "principal_direction"):
            grid = getattr(self, name)
            if grid is not None and grid.shape != self.mean_curvature.shape:
                raise InputError(f"BackShape.{name} must have the curvature maps' shape")
        if self.sagittal_points is not None and self.sagittal_points.shape != (
            len(SAGITTAL_POINTS),
            3,
        ):
            raise InputError("BackShape.sagittal_points must be (5, 3)")
        if self.level_axes is not None and self.level_axes.shape != (3, 3):
            raise InputError("BackShape.level_axes must be (3, 3)")
        _loads("parameters", self.parameters, dict)
        _loads("reasons", self.reasons, dict)

    def landmark(self, name: str) -> np.ndarray | None:
        """The world position of landmark ``name`` (one of :data:`LANDMARKS`), None if absent."""
        return landmark_in(self.landmarks, name)

    def sagittal_point(self, name: str) -> np.ndarray | None:
        """The world position of sagittal point ``name`` (see :data:`SAGITTAL_POINTS`)."""
        try:
            k = SAGITTAL_POINTS.index(name)
        except ValueError:
            raise InputError(
                f"no sagittal point {name!r}; points: {', '.join(SAGITTAL_POINTS)}"
            ) from None
        if self.sagittal_points is None or not np.all(np.isfinite(self.sagittal_points[k])):
            return None
        return np.array(self.sagittal_points[k])

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
            "sagittal_points": {
                name: (None if (p := self.sagittal_point(name)) is None else [float(v) for v in p])
                for name in SAGITTAL_POINTS
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


def _representative(shapes: list[BackShape], names: list[str]) -> BackShape:
    """The frame whose parameters lie closest to the mean (each scaled by its spread)."""
    table = np.full((len(shapes), len(names)), np.nan)
    for i, shape in enumerate(shapes):
        params = shape.parameter_table()
        for j, name in enumerate(names):
            value = params.get(name, {}).get("value")
            if isinstance(value, int | float):
                table[i, j] = float(value)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.nanstd(table, axis=0)
        z = (table - np.nanmean(table, axis=0)) / np.where(scale > 0, scale, 1.0)
    distance = np.nansum(np.where(np.isfinite(z), z * z, 4.0), axis=1)
    return shapes[int(np.argmin(distance))]


def combine(shapes: list[BackShape] | tuple[BackShape, ...]) -> BackShape:
    """Combine the analyses of several frames of one acquisition: mean and spread.

    An acquisition may hold several raster frames (DIERS averages 12, as one frame differs
    from the mean by up to 7 mm / 1.2° through breathing and sway). Frames whose analysis
    is empty (``reason`` set) are left out.

    * every parameter: ``value`` the mean over the frames that have it, ``spread`` the sample
      standard deviation (``ddof=1``; None with one frame); a parameter missing from some
      frames says so in ``reasons``;
    * every landmark and sagittal point: the mean position over the frames that found it,
      its confidence the mean over all frames (0 where not found);
    * the body frame: the mean origin, and the mean axes made orthonormal again;
    * curvature maps and lines: those of the *representative* frame, the one whose
      parameters lie closest to the means (distances in units of each parameter's spread).

    Parameters
    ----------
    shapes : sequence of BackShape
        One analysis per frame, at least one.

    Returns
    -------
    BackShape
        The combined analysis; with a single analysed frame, that frame's analysis. When no
        frame was analysed: empty, with the frames' reasons.

    Raises
    ------
    InputError
        For an empty sequence.
    """
    shapes = list(shapes)
    if not shapes:
        raise InputError("no analysis to combine")
    analysed = [s for s in shapes if not s.reason]
    if not analysed:
        causes = sorted({s.reason for s in shapes})
        return BackShape.empty(f"no frame could be analysed: {'; '.join(causes)}")
    if len(analysed) == 1 and len(shapes) == 1:
        return analysed[0]
    n = len(analysed)
    tables = [s.parameter_table() for s in analysed]
    names: list[str] = []
    for table in tables:
        names += [k for k in table if k not in names]
    parameters: dict[str, dict[str, Any]] = {}
    reasons: dict[str, str] = {}
    for name in names:
        values = [
            float(t[name]["value"])
            for t in tables
            if name in t and isinstance(t[name].get("value"), int | float)
        ]
        unit = next(t[name].get("unit") for t in tables if name in t)
        if not values:
            continue
        parameters[name] = {
            "value": float(np.mean(values)),
            "unit": unit,
            "spread": float(np.std(values, ddof=1)) if len(values) > 1 else None,
        }
        if len(values) < n:
            reasons[name] = f"computed on {len(values)} of {n} frames"

    def mean_points(stack: np.ndarray, labels: tuple[str, ...], what: str) -> np.ndarray:
        found = np.all(np.isfinite(stack), axis=2)
        out = np.full(stack.shape[1:], np.nan)
        for k, label in enumerate(labels):
            if found[:, k].any():
                out[k] = stack[found[:, k], k].mean(axis=0)
                if not found[:, k].all():
                    reasons[label] = f"found in {int(found[:, k].sum())} of {n} frames"
            elif what == "landmark":
                whys = sorted({s.reason_table().get(label, "not found") for s in analysed})
                reasons[label] = "; ".join(whys)
        return out

    landmarks = mean_points(np.stack([s.landmarks for s in analysed]), LANDMARKS, "landmark")
    confidence = np.mean([s.landmark_confidence for s in analysed], axis=0)
    sag = [s.sagittal_points for s in analysed if s.sagittal_points is not None]
    sagittal = mean_points(np.stack(sag), SAGITTAL_POINTS, "point") if sag else None
    frames = [
        s
        for s in analysed
        if np.all(np.isfinite(s.frame_origin)) and np.all(np.isfinite(s.frame_axes))
    ]
    origin, axes = np.full(3, np.nan), np.full((3, 3), np.nan)
    if frames:
        origin = np.mean([s.frame_origin for s in frames], axis=0)
        u, _, vt = np.linalg.svd(np.mean([s.frame_axes for s in frames], axis=0))
        axes = u @ vt  # the nearest orthonormal matrix to the mean axes
    rep = _representative(analysed, list(parameters))
    for what, why in rep.reason_table().items():
        if what not in LANDMARKS and what not in SAGITTAL_POINTS and what not in parameters:
            reasons.setdefault(what, why)
    for shape in shapes:
        if shape.reason:
            reasons.setdefault("frames", f"{len(shapes) - n} of {len(shapes)} frames not analysed")
    return BackShape(
        x0=rep.x0,
        y0=rep.y0,
        spacing=rep.spacing,
        mean_curvature=rep.mean_curvature,
        gaussian_curvature=rep.gaussian_curvature,
        landmarks=landmarks,
        landmark_confidence=confidence,
        frame_origin=origin,
        frame_axes=axes,
        symmetry_line=rep.symmetry_line,
        surface_rotation=rep.surface_rotation,
        midline=rep.midline,
        parameters=json.dumps(parameters),
        reasons=json.dumps(reasons, sort_keys=True),
        max_curvature=rep.max_curvature,
        min_curvature=rep.min_curvature,
        principal_direction=rep.principal_direction,
        sagittal_points=sagittal,
        level_axes=rep.level_axes,
    )
