"""Records of the comparison stage: what it takes of two visits, and what it stores.

A comparison is a stage whose input comes from *two* acquisitions of one patient (the
first multi-acquisition stage kind, see ``docs/comparison.md``). Its input record
:class:`VisitPair` is assembled by the service from each acquisition's stored results (the
mesh, the smoothed surface's measured outline and the analysis's body frame); it is never
stored itself: the stored result names the input results instead (table
``stage_result_input``). Its output :class:`ComparisonRecord` holds the registration and the
per-vertex values of the distance and asymmetry maps, enough to redraw every map without
recomputing; the geometry they are drawn on is visit A's stored mesh.
"""

from __future__ import annotations

import json
from typing import Any, ClassVar

import numpy as np

from rasterserver.errors import InputError
from rasterserver.records import Record
from rasterserver.records_analysis import LANDMARKS

__all__ = ["AsymmetryRecord", "ComparisonRecord", "VisitGeometry", "VisitPair"]


def _check_visit(record: Record, prefix: str) -> None:
    where = f"{type(record).__name__}.{prefix}"
    vertices = getattr(record, f"{prefix}vertices")
    normals = getattr(record, f"{prefix}normals")
    triangles = getattr(record, f"{prefix}triangles")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or normals.shape != vertices.shape:
        raise InputError(f"{where}vertices and normals must both be (N, 3)")
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise InputError(f"{where}triangles must be (M, 3)")
    if getattr(record, f"{prefix}landmarks").shape != (len(LANDMARKS), 3):
        raise InputError(f"{where}landmarks must be ({len(LANDMARKS)}, 3)")
    if getattr(record, f"{prefix}frame_axes").shape != (3, 3):
        raise InputError(f"{where}frame_axes must be (3, 3)")
    if not getattr(record, f"{prefix}spacing") > 0:
        raise InputError(f"{where}spacing must be positive")


class VisitGeometry(Record):
    """One analysed visit as the asymmetry stage sees it (fields as one side of
    :class:`VisitPair`, without the prefix)."""

    kind: ClassVar[str] = "visit-geometry"
    #: What the service builds it from (shown by ``rasterserver plugins --graph``).
    assembled_from: ClassVar[str] = "the stored mesh, surface and backshape of one acquisition"
    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    valid: np.ndarray
    x0: float
    y0: float
    spacing: float
    landmarks: np.ndarray
    frame_origin: np.ndarray
    frame_axes: np.ndarray
    reason: str
    reasons: str
    label: str
    gravity: np.ndarray | None = None

    def validate(self) -> None:
        """Refuse badly shaped meshes, landmark tables or frames."""
        _check_visit(self, "")


class VisitPair(Record):
    """Two analysed visits as a comparison stage sees them (B is registered onto A).

    Per visit (prefix ``a_`` or ``b_``): the mesh (``vertices``, ``triangles``, ``normals``,
    world mm), the smoothed surface's measured outline (``valid``: the grid's cells with a
    height; ``x0``, ``y0``, ``spacing``) and the analysis's body frame (``landmarks`` in the
    order of :data:`~rasterserver.records_analysis.LANDMARKS`, NaN when not found;
    ``frame_origin``, ``frame_axes``; ``reason`` and ``reasons`` (JSON) when it has none),
    ``label``, how messages name the visit (its acquisition uid), and ``gravity``, the
    station's down in the world frame (from the analysis's level frame; None when unknown).
    """

    kind: ClassVar[str] = "visit-pair"
    #: What the service builds it from (shown by ``rasterserver plugins --graph``).
    assembled_from: ClassVar[str] = (
        "the stored mesh, surface and backshape of two acquisitions of one patient"
    )
    a_vertices: np.ndarray
    a_triangles: np.ndarray
    a_normals: np.ndarray
    a_valid: np.ndarray
    a_x0: float
    a_y0: float
    a_spacing: float
    a_landmarks: np.ndarray
    a_frame_origin: np.ndarray
    a_frame_axes: np.ndarray
    a_reason: str
    a_reasons: str
    a_label: str
    b_vertices: np.ndarray
    b_triangles: np.ndarray
    b_normals: np.ndarray
    b_valid: np.ndarray
    b_x0: float
    b_y0: float
    b_spacing: float
    b_landmarks: np.ndarray
    b_frame_origin: np.ndarray
    b_frame_axes: np.ndarray
    b_reason: str
    b_reasons: str
    b_label: str
    a_gravity: np.ndarray | None = None
    b_gravity: np.ndarray | None = None

    def validate(self) -> None:
        """Refuse badly shaped meshes, landmark tables or frames."""
        _check_visit(self, "a_")
        _check_visit(self, "b_")


class ComparisonRecord(Record):
    """The stored comparison of two visits: registration and distance map.

    Attributes
    ----------
    reason : str
        Why the visits could not be registered (then nothing else is meaningful); empty when
        they were.
    transform, start : numpy.ndarray
        ``(4, 4)`` B's world frame onto A's: the result, and the landmark frames' start.
    fitness, rmse : float
        ICP's overlap fraction and inlier rms (mm) at the fine distance.
    points : int
        B's trunk points registered.
    trunk : numpy.ndarray
        ``(K,)`` int64 indices of A's mesh vertices on A's trunk, where the distance map is.
    distance : numpy.ndarray
        ``(K,)`` float64 signed distance (mm) along A's normals to registered B, NaN without
        a counterpart or where not compared; positive where B is posterior of A.
    parameters : str
        JSON: the stage's parameters and the thresholds used.
    displaced : numpy.ndarray or None
        ``(K,)`` bool: trunk vertices not compared, where the visits hold their arms, hands
        or clothing otherwise (version 2); None for comparisons that compared every vertex.
    start_from : str or None
        How the landmark start was made when one visit's VP was not found (version 2); None
        when from both visits' body frames.
    """

    kind: ClassVar[str] = "comparison"
    reason: str
    transform: np.ndarray
    start: np.ndarray
    fitness: float
    rmse: float
    points: int
    trunk: np.ndarray
    distance: np.ndarray
    parameters: str = "{}"
    displaced: np.ndarray | None = None
    start_from: str | None = None

    def validate(self) -> None:
        """Refuse maps whose indices and values differ in length, or bad transforms."""
        for name in ("transform", "start"):
            if getattr(self, name).shape != (4, 4):
                raise InputError(f"ComparisonRecord.{name} must be (4, 4)")
        if self.trunk.shape != self.distance.shape:
            raise InputError("ComparisonRecord.trunk and distance differ in length")
        if self.displaced is not None and (
            self.displaced.dtype != np.bool_ or self.displaced.shape != self.trunk.shape
        ):
            raise InputError("ComparisonRecord.displaced must be one bool per trunk vertex")

    @property
    def refused(self) -> bool:
        """True when the visits could not be registered (:attr:`reason` says why)."""
        return bool(self.reason)

    def parameter_table(self) -> dict[str, Any]:
        """The parameters and thresholds the comparison used."""
        value = json.loads(self.parameters)
        if not isinstance(value, dict):
            raise InputError("ComparisonRecord.parameters is not a JSON object")
        return value


class AsymmetryRecord(Record):
    """One visit's asymmetry map: the back against its mirror image (Komeili et al. 2015).

    Attributes
    ----------
    reason : str
        Why the map was refused (no body frame, too little trunk, the mirror not fitted).
    trunk : numpy.ndarray
        ``(K,)`` int64 indices of the visit's mesh vertices on its trunk.
    asymmetry : numpy.ndarray
        ``(K,)`` float64 signed distance (mm) to the fitted mirror image, NaN without one;
        positive where the back is more posterior than its mirror image.
    transform : numpy.ndarray
        ``(4, 4)`` the fit of the mirror image onto the back (after the reflection).
    fitness, rmse : float
        The mirror fit's overlap and inlier rms (mm).
    parameters : str
        JSON: the stage's parameters and thresholds.
    """

    kind: ClassVar[str] = "asymmetry"
    reason: str
    trunk: np.ndarray
    asymmetry: np.ndarray
    transform: np.ndarray
    fitness: float
    rmse: float
    parameters: str = "{}"

    def validate(self) -> None:
        """Refuse a map whose indices and values differ in length."""
        if self.trunk.shape != self.asymmetry.shape:
            raise InputError("AsymmetryRecord.trunk and asymmetry differ in length")
        if self.transform.shape != (4, 4):
            raise InputError("AsymmetryRecord.transform must be (4, 4)")

    @property
    def refused(self) -> bool:
        """True when there is no map (:attr:`reason` says why)."""
        return bool(self.reason)
