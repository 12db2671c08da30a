"""What a comparison works on and gives: a visit's records, its body frame, the registration
of one visit onto another and a distance map over a mesh's vertices."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rasterserver.comparison.geometry import rotation_angle, vertex_areas
from rasterserver.records_analysis import BackShape, landmark_in
from rasterserver.records_surface import MeshRecord, Surface


@dataclass(frozen=True, eq=False)
class BodyFrame:
    """The part of a back-shape analysis a comparison uses: landmarks and body frame.

    Attributes
    ----------
    frame_origin : numpy.ndarray
        ``(3,)`` DM (world mm), NaN without a frame.
    frame_axes : numpy.ndarray
        ``(3, 3)`` rows: transverse, vertical, sagittal unit axes.
    landmarks : numpy.ndarray
        ``(len(LANDMARKS), 3)`` world mm in the order of
        :data:`~rasterserver.records_analysis.LANDMARKS`, NaN when not found.
    reason : str
        Why the analysis found nothing, if it did not.
    reasons : str
        JSON object: what could not be computed, and why.
    gravity : numpy.ndarray or None
        ``(3,)`` the station's down (world), from the analysis's level frame; None when the
        analysis does not say.
    """

    frame_origin: np.ndarray
    frame_axes: np.ndarray
    landmarks: np.ndarray
    reason: str = ""
    reasons: str = "{}"
    gravity: np.ndarray | None = None

    @classmethod
    def of(cls, shape: BackShape | BodyFrame) -> BodyFrame:
        """The body frame of an analysis."""
        if isinstance(shape, BodyFrame):
            return shape
        return cls(
            np.asarray(shape.frame_origin, dtype=float),
            np.asarray(shape.frame_axes, dtype=float),
            np.asarray(shape.landmarks, dtype=float),
            shape.reason,
            shape.reasons,
            None if shape.level_axes is None else np.asarray(shape.level_axes[1], dtype=float),
        )

    def landmark(self, name: str) -> np.ndarray | None:
        """World position of landmark ``name``, None when not found."""
        return landmark_in(self.landmarks, name)

    def reason_table(self) -> dict[str, str]:
        """What could not be computed, and why."""
        value = json.loads(self.reasons or "{}")
        return value if isinstance(value, dict) else {}


@dataclass(frozen=True)
class Visit:
    """What the comparison needs of one analysed acquisition.

    Attributes
    ----------
    surface : Surface
        The smoothed surface (its measured outline bounds the trunk).
    mesh : MeshRecord
        The mesh of that surface (normals facing the camera).
    shape : BackShape or BodyFrame
        The back-shape analysis (landmarks, body frame).
    label : str
        How messages name the visit (an acquisition uid, a date).
    """

    surface: Surface
    mesh: MeshRecord
    shape: BackShape | BodyFrame
    label: str = ""


@dataclass(frozen=True)
class Registration:
    """Visit B moved onto visit A.

    Attributes
    ----------
    transform : numpy.ndarray
        ``(4, 4)`` rigid transform from B's world frame to A's (``p_a = R p_b + t``).
    start : numpy.ndarray
        ``(4, 4)`` the landmark frames' transform ICP started from.
    fitness : float
        Fraction of B's trunk points with a counterpart on A's trunk within
        ``Thresholds.fine_distance`` (open3d's ``evaluate_registration``).
    rmse : float
        Rms distance of those counterparts (mm).
    points : int
        B's trunk points used.
    start_from : str or None
        None when ICP started from both visits' body frames; otherwise how the start was
        made (:func:`~rasterserver.comparison.pair_frames`: one visit without VP).
    """

    transform: np.ndarray
    start: np.ndarray
    fitness: float
    rmse: float
    points: int
    start_from: str | None = None

    def summary(self) -> dict[str, Any]:
        """JSON-ready: transform, landmark start, fitness, rmse, points, and what ICP added to
        the landmark start (angle and translation of ``transform @ inv(start)``)."""
        extra = self.transform @ np.linalg.inv(self.start)
        return {
            "transform": [[float(v) for v in row] for row in self.transform],
            "landmark_start": [[float(v) for v in row] for row in self.start],
            "fitness": float(self.fitness),
            "rmse_mm": float(self.rmse),
            "points": int(self.points),
            "landmark_start_from": self.start_from or "VP, DL and DR of both visits",
            "icp_rotation_deg": rotation_angle(extra[:3, :3]),
            "icp_translation_mm": float(np.linalg.norm(extra[:3, 3])),
        }


@dataclass(frozen=True)
class DistanceMap:
    """A signed scalar per vertex of a (trunk) mesh, in mm.

    Attributes
    ----------
    vertices : numpy.ndarray
        ``(N, 3)`` world mm (visit A's frame).
    triangles : numpy.ndarray
        ``(M, 3)`` int32 vertex indices.
    normals : numpy.ndarray
        ``(N, 3)`` unit vertex normals, facing the camera (posterior).
    distance : numpy.ndarray
        ``(N,)`` float64 signed distance (mm), NaN where there is no counterpart.
    what : str
        What the value is (for file headers and plots).
    displaced : numpy.ndarray or None
        ``(N,)`` bool: vertices not compared, in regions where the visits' arms, hands or
        clothing lie otherwise (:func:`~rasterserver.comparison.displaced_regions`); their
        distance is NaN. None: every vertex compared.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    distance: np.ndarray
    what: str = "signed distance (mm)"
    displaced: np.ndarray | None = None
    area: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "area", vertex_areas(self.vertices, self.triangles))

    def statistics(self) -> dict[str, Any]:
        """rms, largest absolute value (signed, and where), areas beyond ±2 and ±5 mm.

        Returns
        -------
        dict
            ``vertices``, ``measured`` (vertices with a value), ``overlap`` (their area
            fraction), ``displaced`` (the area fraction not compared: arms, hands or
            clothing placed otherwise), ``rms_mm``, ``mean_mm``, ``max_abs_mm`` (signed),
            ``max_abs_at`` (world mm), ``area_mm2`` (measured), ``area_above_2mm_mm2``,
            ``area_below_minus_2mm_mm2``, ``area_above_5mm_mm2``, ``area_below_minus_5mm_mm2``.
            Values are None when nothing was measured.
        """
        d = self.distance
        ok = np.isfinite(d)
        total = float(self.area.sum())
        out: dict[str, Any] = {
            "vertices": int(d.size),
            "measured": int(ok.sum()),
            "overlap": float(self.area[ok].sum() / total) if total > 0 else 0.0,
            "displaced": (
                float(self.area[self.displaced].sum() / total)
                if total > 0 and self.displaced is not None
                else 0.0
            ),
        }
        if not ok.any():
            return out | dict.fromkeys(
                ("rms_mm", "mean_mm", "max_abs_mm", "max_abs_at", "area_mm2"), None
            )
        w = self.area[ok]
        v = d[ok]
        k = int(np.argmax(np.abs(v)))
        out |= {
            "rms_mm": float(np.sqrt(np.average(v * v, weights=w))) if w.sum() > 0 else None,
            "mean_mm": float(np.average(v, weights=w)) if w.sum() > 0 else None,
            "max_abs_mm": float(v[k]),
            "max_abs_at": [float(c) for c in self.vertices[ok][k]],
            "area_mm2": float(w.sum()),
        }
        for limit in (2, 5):
            out[f"area_above_{limit}mm_mm2"] = float(w[v > limit].sum())
            out[f"area_below_minus_{limit}mm_mm2"] = float(w[v < -limit].sum())
        return out
