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

__all__ = ["ComparisonRecord", "VisitPair"]


def _check_visit(record: Record, side: str) -> None:
    vertices = getattr(record, f"{side}_vertices")
    normals = getattr(record, f"{side}_normals")
    triangles = getattr(record, f"{side}_triangles")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or normals.shape != vertices.shape:
        raise InputError(f"VisitPair.{side}: vertices and normals must both be (N, 3)")
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise InputError(f"VisitPair.{side}: triangles must be (M, 3)")
    if getattr(record, f"{side}_landmarks").shape != (len(LANDMARKS), 3):
        raise InputError(f"VisitPair.{side}: landmarks must be ({len(LANDMARKS)}, 3)")
    if getattr(record, f"{side}_frame_axes").shape != (3, 3):
        raise InputError(f"VisitPair.{side}: frame axes must be (3, 3)")
    if getattr(record, f"{side}_spacing") <= 0:
        raise InputError(f"VisitPair.{side}: grid spacing must be positive")


class VisitPair(Record):
    """Two analysed visits as a comparison stage sees them (B is registered onto A).

    Per visit (prefix ``a_`` or ``b_``): the mesh (``vertices``, ``triangles``, ``normals``,
    world mm), the smoothed surface's measured outline (``valid``: the grid's cells with a
    height; ``x0``, ``y0``, ``spacing``) and the analysis's body frame (``landmarks`` in the
    order of :data:`~rasterserver.records_analysis.LANDMARKS`, NaN when not found;
    ``frame_origin``, ``frame_axes``; ``reason`` and ``reasons`` (JSON) when it has none),
    and ``label``, how messages name the visit (its acquisition uid).
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

    def validate(self) -> None:
        """Refuse badly shaped meshes, landmark tables or frames."""
        _check_visit(self, "a")
        _check_visit(self, "b")


class ComparisonRecord(Record):
    """The stored comparison of two visits: registration, distance map, asymmetry maps.

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
        a counterpart; positive where B is posterior of A.
    a_asymmetry_trunk, b_asymmetry_trunk : numpy.ndarray
        Indices of each visit's mesh vertices where its asymmetry map is.
    a_asymmetry, b_asymmetry : numpy.ndarray
        Each visit's asymmetry map (mm; empty when refused).
    a_asymmetry_reason, b_asymmetry_reason : str
        Why a visit's asymmetry map was refused.
    parameters : str
        JSON: the stage's parameters and the thresholds used.
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
    a_asymmetry_trunk: np.ndarray
    a_asymmetry: np.ndarray
    a_asymmetry_reason: str
    b_asymmetry_trunk: np.ndarray
    b_asymmetry: np.ndarray
    b_asymmetry_reason: str
    parameters: str = "{}"

    def validate(self) -> None:
        """Refuse maps whose indices and values differ in length, or bad transforms."""
        for name in ("transform", "start"):
            if getattr(self, name).shape != (4, 4):
                raise InputError(f"ComparisonRecord.{name} must be (4, 4)")
        for index, values in (
            ("trunk", "distance"),
            ("a_asymmetry_trunk", "a_asymmetry"),
            ("b_asymmetry_trunk", "b_asymmetry"),
        ):
            if getattr(self, index).shape != getattr(self, values).shape:
                raise InputError(f"ComparisonRecord.{index} and {values} differ in length")

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
