"""The seed's control-point system: aluminium control planes with seven black holes each.

Physical model (after the seed's Fig. 8): a cast-aluminium base far behind, and two control
planes (sandblasted aluminium, diffuse albedo 0.7) mounted parallel to it on columns of two
lengths: *high* (Z = −100 mm, nearer the camera) and *low* (Z = +100 mm). Each plate bears
seven control points, holes underlaid with black velvet that image dark (albedo 0.02).
"At each of three possible lateral locations a high and a low position of the control plane
is used, and each is recorded with the projector on and off. Thus, a total of six frames":
here the two plates are moved through three configurations so that every lateral location
(X = −180, 0, +180 mm) carries the high plate once and the low plate once; each
configuration is recorded with the projector on (raster lines) and off (control points),
i.e. 3 × 2 = 6 frames.

The holes are modelled as albedo (black discs on the plate's surface), not as geometry: the
control point is the centre of the hole in the plate's front surface, which is what a
photogrammetrist measures, and the disc edges are exact to the renderer's sub-sampling.

Hole pattern on each plate (plate coordinates, mm, x to the right, y down, origin at the
plate centre): a 2 × 3 grid at x = ±40, y = −120, 0, +120 (indices 0–5, row by row) and a
marker at (+20, +60) (index 6). The marker breaks every symmetry of the grid, so the
pattern identifies each point and the plate's orientation; the high plate sits 60 mm above
the low one, which tells the two plates apart in every configuration.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from rasterserver.errors import InputError
from rasterserver.simulator.scene import Scene, SceneObject

__all__ = [
    "CONFIGURATIONS",
    "CONTROL_POINTS_FORMAT",
    "HOLE_LAYOUT",
    "ControlPoint",
    "PlatePlacement",
    "control_points",
    "make_calibration_body",
    "plate_placements",
    "write_control_points",
]

CONTROL_POINTS_FORMAT = "rasterserver.control_points/1"

#: Hole centres in plate coordinates (mm): 2 × 3 grid, then the orientation marker.
HOLE_LAYOUT: np.ndarray = np.array(
    [
        *([-40.0, -120.0], [40.0, -120.0]),
        *([-40.0, 0.0], [40.0, 0.0]),
        *([-40.0, 120.0], [40.0, 120.0]),
        [20.0, 60.0],
    ]
)
HOLE_LAYOUT.setflags(write=False)

PLATE_SIZE = (150.0, 400.0)  # width (X), height (Y), mm
HEIGHTS = {"high": -100.0, "low": 100.0}  # plate surface Z, mm
LATERAL = {"left": -180.0, "centre": 0.0, "right": 180.0}  # plate centre X, mm
PLATE_Y = {"high": -30.0, "low": 30.0}  # plate centre Y, mm
BASE_Z = 300.0

#: (high plate's lateral location, low plate's lateral location) per configuration.
CONFIGURATIONS: tuple[tuple[str, str], ...] = (
    ("left", "centre"),
    ("centre", "right"),
    ("right", "left"),
)


@dataclass(frozen=True)
class PlatePlacement:
    """Where one control plane is mounted in one configuration.

    Attributes
    ----------
    plate : str
        ``"high"`` (Z = −100, nearer the camera) or ``"low"`` (Z = +100).
    lateral : str
        ``"left"``, ``"centre"`` or ``"right"`` (X = −180, 0, +180).
    centre : tuple of float
        Centre of the plate's front surface (world mm).
    size : tuple of float
        Width and height (mm).
    """

    plate: str
    lateral: str
    centre: tuple[float, float, float]
    size: tuple[float, float] = PLATE_SIZE

    def holes(self) -> np.ndarray:
        """World coordinates ``(7, 3)`` of the plate's control points, in index order."""
        x, y, z = self.centre
        return np.column_stack(
            [HOLE_LAYOUT[:, 0] + x, HOLE_LAYOUT[:, 1] + y, np.full(len(HOLE_LAYOUT), z)]
        )


@dataclass(frozen=True)
class ControlPoint:
    """One control point with its identity.

    Attributes
    ----------
    id : str
        ``"c<configuration>-<plate>-<index>"``, e.g. ``"c0-high-6"``.
    configuration : int
        0, 1 or 2.
    plate : str
        ``"high"`` or ``"low"``.
    lateral : str
        Lateral location of the plate.
    index : int
        0–5 for the grid (row by row, left to right), 6 for the orientation marker.
    x, y, z : float
        Centre of the hole in the plate's front surface, world mm.
    """

    id: str
    configuration: int
    plate: str
    lateral: str
    index: int
    x: float
    y: float
    z: float


def _check_configuration(configuration: int) -> int:
    if isinstance(configuration, bool) or not isinstance(configuration, int | np.integer):
        raise InputError(f"configuration must be an integer, got {configuration!r}")
    if not 0 <= configuration < len(CONFIGURATIONS):
        raise InputError(f"configuration must be 0..{len(CONFIGURATIONS) - 1}, got {configuration}")
    return int(configuration)


def plate_placements(configuration: int) -> tuple[PlatePlacement, PlatePlacement]:
    """Return the (high, low) plate placements of a configuration (0, 1 or 2)."""
    k = _check_configuration(configuration)
    high, low = CONFIGURATIONS[k]
    return (
        PlatePlacement("high", high, (LATERAL[high], PLATE_Y["high"], HEIGHTS["high"])),
        PlatePlacement("low", low, (LATERAL[low], PLATE_Y["low"], HEIGHTS["low"])),
    )


def control_points(configurations: int | Iterable[int] | None = None) -> list[ControlPoint]:
    """Return the control points of one, several or (by default) all configurations.

    Parameters
    ----------
    configurations : int or iterable of int, optional
        Which configurations; all three when omitted.

    Returns
    -------
    list of ControlPoint
        Ordered by configuration, plate (high, low) and index: 14 per configuration.
    """
    if configurations is None:
        ks: list[int] = list(range(len(CONFIGURATIONS)))
    elif isinstance(configurations, int | np.integer):
        ks = [int(configurations)]
    else:
        ks = [int(k) for k in configurations]
    points: list[ControlPoint] = []
    for k in ks:
        for placement in plate_placements(k):
            for i, (x, y, z) in enumerate(placement.holes()):
                points.append(
                    ControlPoint(
                        f"c{k}-{placement.plate}-{i}",
                        k,
                        placement.plate,
                        placement.lateral,
                        i,
                        float(x),
                        float(y),
                        float(z),
                    )
                )
    return points


def write_control_points(path: str | Path, points: Iterable[ControlPoint]) -> Path:
    """Write control points as JSON (``.json``) or CSV (any other suffix).

    JSON: ``{"format": "rasterserver.control_points/1", "units": "mm", "frame": ...,
    "hole_layout": ..., "points": [{"id", "configuration", "plate", "lateral", "index",
    "x", "y", "z"}, ...]}``. CSV: a header row with the same point fields, one point a row.

    Parameters
    ----------
    path : str or Path
        Target file.
    points : iterable of ControlPoint
        What to write, e.g. :func:`control_points`.

    Returns
    -------
    Path
    """
    path = Path(path)
    rows = [asdict(p) for p in points]
    if path.suffix.lower() == ".json":
        document = {
            "format": CONTROL_POINTS_FORMAT,
            "units": "mm",
            "frame": (
                "world: X right, Y down, Z away from the camera; the point is the centre of "
                "the hole in the plate's front surface"
            ),
            "hole_layout": {
                "plate_coordinates_mm": HOLE_LAYOUT.tolist(),
                "description": "indices 0-5: 2x3 grid row by row; 6: orientation marker",
            },
            "points": rows,
        }
        path.write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    else:
        with path.open("w", newline="", encoding="utf-8") as fh:
            writer = csv.DictWriter(fh, fieldnames=[f for f in ControlPoint.__annotations__])
            writer.writeheader()
            writer.writerows(rows)
    return path


@dataclass(frozen=True)
class HoleAlbedo:
    """Plate albedo with dark discs (the velvet-lined holes) at given centres.

    Picklable; evaluated on world points of a fronto-parallel plate, so the distance in X–Y
    is the distance within the plate.

    Attributes
    ----------
    centres : tuple of (float, float)
        Hole centres (world X, Y, mm).
    radius : float
        Hole radius (mm).
    plate : float
        Albedo of the sandblasted aluminium.
    hole : float
        Albedo of the velvet.
    """

    centres: tuple[tuple[float, float], ...]
    radius: float = 4.5
    plate: float = 0.7
    hole: float = 0.02

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Return the albedo ``(N,)`` at world points ``(N, 3)``."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        c = np.asarray(self.centres, dtype=float)
        d2 = ((pts[:, None, :2] - c[None]) ** 2).sum(-1).min(1)
        return np.where(d2 <= self.radius**2, self.hole, self.plate)


def _box(centre: np.ndarray, size: tuple[float, float], depth: float) -> o3d.geometry.TriangleMesh:
    """A plate as a box whose front face (−Z) passes through ``centre``."""
    w, h = size
    box = o3d.geometry.TriangleMesh.create_box(w, h, depth)
    box.translate(centre - np.array([w / 2, h / 2, 0.0]))
    box.compute_vertex_normals()
    return box


def make_calibration_body(
    configuration: int,
    *,
    hole_radius: float = 4.5,
    plate_albedo: float = 0.7,
    hole_albedo: float = 0.02,
    base: bool = True,
    base_albedo: float = 0.3,
) -> Scene:
    """Build the control-point system in one of its three configurations.

    Parameters
    ----------
    configuration : int
        0, 1 or 2: which lateral locations the high and the low plate occupy
        (:data:`CONFIGURATIONS`).
    hole_radius : float, optional
        Radius of the holes (mm), in [1, 15]; 4.5 mm is ~4.5 pixels at the default station.
    plate_albedo, hole_albedo : float, optional
        Albedo of the aluminium and of the velvet; the holes must be darker.
    base : bool, optional
        Include the cast base (a large plate at Z = +300 mm) behind the control planes.
    base_albedo : float, optional
        Albedo of the base.

    Returns
    -------
    Scene
        Objects ``"plate-high"`` and ``"plate-low"`` (10 mm thick boxes whose front faces
        carry the holes) and optionally ``"base"``. Landmarks: ``"control_points"``
        ``(14, 3)`` in :func:`control_points` order and one ``"cp/<id>"`` point per control
        point. Metadata: configuration, plate placements, hole radius and layout, and the
        control points as records.

    Raises
    ------
    InputError
        For an unknown configuration or unusable radius/albedo values.
    """
    placements = plate_placements(configuration)
    r = float(hole_radius)
    if not (math.isfinite(r) and 1.0 <= r <= 15.0):
        raise InputError(f"hole_radius must lie in [1, 15] mm, got {hole_radius!r}")
    for name, value in (
        ("plate_albedo", plate_albedo),
        ("hole_albedo", hole_albedo),
        ("base_albedo", base_albedo),
    ):
        if not (math.isfinite(value) and 0.0 <= value <= 1.0):
            raise InputError(f"{name} must lie in [0, 1], got {value!r}")
    if hole_albedo >= plate_albedo:
        raise InputError("hole_albedo must be below plate_albedo, or the holes cannot be seen")
    objects = []
    for placement in placements:
        holes = placement.holes()
        albedo = HoleAlbedo(
            tuple((float(x), float(y)) for x, y in holes[:, :2]), r, plate_albedo, hole_albedo
        )
        mesh = _box(np.asarray(placement.centre), placement.size, 10.0)
        objects.append(SceneObject(f"plate-{placement.plate}", mesh, albedo))
    if base:
        objects.append(
            SceneObject(
                "base", _box(np.array([0.0, 0.0, BASE_Z]), (900.0, 900.0), 40.0), base_albedo
            )
        )
    points = control_points(configuration)
    landmarks: dict[str, np.ndarray] = {
        "control_points": np.array([[p.x, p.y, p.z] for p in points])
    }
    landmarks.update({f"cp/{p.id}": np.array([p.x, p.y, p.z]) for p in points})
    return Scene(
        objects=objects,
        landmarks=landmarks,
        metadata={
            "kind": "calibration_body",
            "configuration": int(configuration),
            "plates": [asdict(p) for p in placements],
            "hole_radius_mm": r,
            "hole_layout_mm": HOLE_LAYOUT.tolist(),
            "plate_albedo": plate_albedo,
            "hole_albedo": hole_albedo,
            "control_points": [asdict(p) for p in points],
        },
    )
