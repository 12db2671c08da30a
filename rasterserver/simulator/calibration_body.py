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

*The body as a clinic's camera sees it* (``make_calibration_body(k, **REAL_BODY)`` or
:func:`real_body`): the cast base is as bright as the plates (albedo 0.7, with a cast
mottling), the plates stand on columns whose sides show beyond the plates' top and bottom
edges and join the plates to the base in the image, the plates' sides show, the base carries
dark mounting holes where the unused columns would stand, and the light is uneven (a lamp
up and to one side: the reflected light varies about 1.8:1 over the body,
:class:`UnevenLight`).
Nothing separates a plate from the base by brightness there: only the holes' pattern (and
the depth steps of the raster lines in the projector-on frame) tell where a plate is. Any
seven-point hole layout may be given (``layout=``; :func:`random_hole_layout`).

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
from collections.abc import Callable, Iterable
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
    "REAL_BODY",
    "ControlPoint",
    "LitAlbedo",
    "PlatePlacement",
    "UnevenLight",
    "check_hole_layout",
    "control_points",
    "make_calibration_body",
    "plate_placements",
    "random_hole_layout",
    "real_body",
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
COLUMN_RADIUS = 14.0  # mm; the columns stand 10 mm beyond the plates' top and bottom edges
COLUMN_INSET = 4.0  # mm from the plate's top/bottom edge to the column's axis
MOUNT_HOLE_RADIUS = 5.0  # mm, the base's threaded holes for the columns

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
    layout: tuple[tuple[float, float], ...] = tuple(
        (float(x), float(y)) for x, y in HOLE_LAYOUT
    )

    def holes(self) -> np.ndarray:
        """World coordinates ``(7, 3)`` of the plate's control points, in index order."""
        x, y, z = self.centre
        layout = np.asarray(self.layout, dtype=float)
        return np.column_stack(
            [layout[:, 0] + x, layout[:, 1] + y, np.full(len(layout), z)]
        )

    def columns(self) -> np.ndarray:
        """Axis positions ``(2, 2)`` (world X, Y) of the plate's two columns: top and bottom."""
        x, y, _ = self.centre
        reach = self.size[1] / 2 - COLUMN_INSET
        return np.array([[x, y - reach], [x, y + reach]])


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


def check_hole_layout(
    layout: np.ndarray | None, *, hole_radius: float = 4.5, size: tuple[float, float] = PLATE_SIZE
) -> np.ndarray:
    """Return a usable seven-hole layout ``(7, 2)`` (plate mm), the default when ``None``.

    Raises
    ------
    InputError
        Not seven finite points, a hole (with a 5 mm rim) not on the plate, or two holes
        closer than four radii (their images would merge).
    """
    if layout is None:
        return HOLE_LAYOUT.copy()
    arr = np.asarray(layout, dtype=float)
    if arr.shape != (7, 2) or not np.isfinite(arr).all():
        raise InputError(f"a hole layout must be 7 finite points (x, y) in mm, got {arr.shape}")
    half = np.array(size) / 2 - hole_radius - 5.0
    if (np.abs(arr) > half).any():
        raise InputError(f"a hole of the layout lies off the {size[0]:g} x {size[1]:g} mm plate")
    gaps = np.linalg.norm(arr[:, None] - arr[None], axis=2)[np.triu_indices(7, 1)]
    if gaps.min() < 4 * hole_radius:
        raise InputError(f"two holes of the layout are {gaps.min():.1f} mm apart, closer than "
                         f"four radii ({4 * hole_radius:g} mm)")
    return arr


def random_hole_layout(
    rng: np.random.Generator, *, min_gap: float = 45.0, size: tuple[float, float] = PLATE_SIZE
) -> np.ndarray:
    """Draw an irregular seven-hole layout (plate mm) with holes ``min_gap`` mm apart or more.

    Holes stay 20 mm inside the plate's edges. Random points have no symmetry (the chance of
    an affine self-map is nil), so every such layout identifies its points; the calibration
    checks that anyway.
    """
    half = np.array(size) / 2 - 20.0
    for _ in range(10_000):
        points: list[np.ndarray] = []
        while len(points) < 7:
            p = rng.uniform(-half, half)
            if all(np.linalg.norm(p - q) >= min_gap for q in points):
                points.append(p)
            elif rng.random() < 0.01:
                break
        if len(points) == 7:
            return np.round(np.array(points), 3)
    raise InputError(f"cannot place seven holes {min_gap:g} mm apart on the plate")


def plate_placements(
    configuration: int, *, layout: np.ndarray | None = None
) -> tuple[PlatePlacement, PlatePlacement]:
    """Return the (high, low) plate placements of a configuration (0, 1 or 2).

    ``layout`` : the seven holes in plate coordinates (mm), :data:`HOLE_LAYOUT` by default.
    """
    k = _check_configuration(configuration)
    high, low = CONFIGURATIONS[k]
    holes = tuple((float(x), float(y)) for x, y in check_hole_layout(layout))
    return (
        PlatePlacement("high", high, (LATERAL[high], PLATE_Y["high"], HEIGHTS["high"]),
                       layout=holes),
        PlatePlacement("low", low, (LATERAL[low], PLATE_Y["low"], HEIGHTS["low"]), layout=holes),
    )


def control_points(
    configurations: int | Iterable[int] | None = None, *, layout: np.ndarray | None = None
) -> list[ControlPoint]:
    """Return the control points of one, several or (by default) all configurations.

    Parameters
    ----------
    configurations : int or iterable of int, optional
        Which configurations; all three when omitted.
    layout : numpy.ndarray, optional
        ``(7, 2)`` hole layout (plate mm); :data:`HOLE_LAYOUT` by default.

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
        for placement in plate_placements(k, layout=layout):
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


def write_control_points(
    path: str | Path, points: Iterable[ControlPoint], *, layout: np.ndarray | None = None
) -> Path:
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
    layout : numpy.ndarray, optional
        The hole layout the points were made with (JSON only); :data:`HOLE_LAYOUT` by default.

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
            "hole_layout": (
                {
                    "plate_coordinates_mm": HOLE_LAYOUT.tolist(),
                    "description": "indices 0-5: 2x3 grid row by row; 6: orientation marker",
                }
                if layout is None
                else {
                    "plate_coordinates_mm": check_hole_layout(layout).tolist(),
                    "description": "hole centres by index, plate x right, y down, mm",
                }
            ),
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


@dataclass(frozen=True)
class UnevenLight:
    """Uneven illumination: a factor in (0, 1] on the light a surface sends to the camera.

    A lamp at ``source`` (world mm) adds to a uniform share ``floor``; its share falls with the
    squared distance and is 1 at ``reference`` mm from the lamp. Only smooth in space: it
    does not depend on the surface's normal (neither does the renderer's ambient light).
    Picklable; evaluated from several threads.

    Attributes
    ----------
    source : tuple of float
        Lamp position (world mm).
    floor : float
        Uniform share of the light, in [0, 1).
    reference : float
        Distance (mm) at which the lamp's share is whole; nearer points are clipped to 1.
    """

    source: tuple[float, float, float] = (-1500.0, -1200.0, -400.0)
    floor: float = 0.3
    reference: float = 1600.0

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Return the factor ``(N,)`` at world points ``(N, 3)``."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        d2 = ((pts - np.asarray(self.source)) ** 2).sum(axis=1)
        lamp = np.minimum(self.reference**2 / np.maximum(d2, 1e-9), 1.0)
        return self.floor + (1.0 - self.floor) * lamp


@dataclass(frozen=True)
class LitAlbedo:
    """An albedo (constant or function) times a cast mottling and an :class:`UnevenLight`.

    Attributes
    ----------
    albedo : float or callable
        The surface's reflectance.
    light : UnevenLight or None
        Illumination factor; ``None`` for uniform light.
    mottling : float
        Relative amplitude of the cast aluminium's low-frequency mottling (0: none); a fixed
        sum of sines over X, Y with wavelengths of 70-170 mm.
    holes : tuple of (float, float)
        Dark discs (world X, Y) on a fronto-parallel surface: the base's mounting holes.
    hole_radius : float
        Their radius (mm).
    hole_albedo : float
        Their reflectance.
    """

    albedo: float | Callable[[np.ndarray], np.ndarray]
    light: UnevenLight | None = None
    mottling: float = 0.0
    holes: tuple[tuple[float, float], ...] = ()
    hole_radius: float = MOUNT_HOLE_RADIUS
    hole_albedo: float = 0.05

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Return the reflected share ``(N,)`` at world points ``(N, 3)``."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        if callable(self.albedo):
            out = np.asarray(self.albedo(pts), dtype=float)
        else:
            out = np.full(len(pts), float(self.albedo))
        if self.mottling:
            x, y = pts[:, 0], pts[:, 1]
            wave = (np.sin(x / 27.0 + 0.3) * np.sin(y / 19.0 + 1.1)
                    + 0.6 * np.sin((x + 0.7 * y) / 11.0 + 2.0))
            out = out * (1.0 + self.mottling * wave / 1.6)
        if self.holes:
            c = np.asarray(self.holes, dtype=float)
            d2 = ((pts[:, None, :2] - c[None]) ** 2).sum(-1).min(1)
            out = np.where(d2 <= self.hole_radius**2, self.hole_albedo, out)
        if self.light is not None:
            out = out * self.light(pts)
        return out


#: Options of :func:`make_calibration_body` for the body as a clinic's camera sees it.
REAL_BODY: dict[str, object] = {
    "base_albedo": 0.75,  # 300 mm further from the lamp than the high plate: as bright
    "columns": True,
    "mount_holes": True,
    "mottling": 0.05,
    "light": UnevenLight(),
}


def real_body(configuration: int, **options: object) -> Scene:
    """The control-point body with the bright base, columns, mounting holes and uneven light.

    ``make_calibration_body(configuration, **REAL_BODY)`` with ``options`` overriding.
    """
    return make_calibration_body(configuration, **{**REAL_BODY, **options})  # type: ignore[arg-type]


def _column(xy: np.ndarray, z0: float, z1: float) -> o3d.geometry.TriangleMesh:
    """A column of radius :data:`COLUMN_RADIUS` along Z from ``z0`` to ``z1`` at ``xy``."""
    cyl = o3d.geometry.TriangleMesh.create_cylinder(COLUMN_RADIUS, z1 - z0, resolution=48)
    cyl.translate(np.array([xy[0], xy[1], (z0 + z1) / 2]))
    cyl.compute_vertex_normals()
    return cyl


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
    layout: np.ndarray | None = None,
    columns: bool = False,
    mount_holes: bool = False,
    mottling: float = 0.0,
    light: UnevenLight | None = None,
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
        Albedo of the base (0.3: darker than the plates; the seed's cast base is as bright as
        the plates, 0.7, see :data:`REAL_BODY`).
    layout : numpy.ndarray, optional
        ``(7, 2)`` hole layout in plate coordinates (mm), :data:`HOLE_LAYOUT` by default.
    columns : bool, optional
        Stand each plate on two columns (radius 14 mm, from the plate's back to the base) at
        its top and bottom edges; they show 10 mm beyond the plate's outline and, seen in
        perspective, join it to the base in the image.
    mount_holes : bool, optional
        Dark threaded holes in the base (radius 5 mm) at every column position of the three
        configurations; those of the other configurations show as dark spots on the base.
    mottling : float, optional
        Relative amplitude of the cast base's low-frequency albedo mottling.
    light : UnevenLight, optional
        Uneven illumination of everything (plates, columns, base); uniform when omitted.

    Returns
    -------
    Scene
        Objects ``"plate-high"`` and ``"plate-low"`` (10 mm thick boxes whose front faces
        carry the holes), optionally ``"column-high-0"`` ... and ``"base"``. Landmarks:
        ``"control_points"`` ``(14, 3)`` in :func:`control_points` order and one
        ``"cp/<id>"`` point per control point. Metadata: configuration, plate placements,
        hole radius and layout, the body's options, and the control points as records.

    Raises
    ------
    InputError
        For an unknown configuration or unusable radius/albedo values.
    """
    _check_configuration(configuration)
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
    if not (math.isfinite(mottling) and 0.0 <= mottling <= 0.5):
        raise InputError(f"mottling must lie in [0, 0.5], got {mottling!r}")
    layout_mm = check_hole_layout(layout, hole_radius=r)
    placements = plate_placements(configuration, layout=layout_mm)
    objects = []
    for placement in placements:
        holes = placement.holes()
        albedo: float | Callable[[np.ndarray], np.ndarray] = HoleAlbedo(
            tuple((float(x), float(y)) for x, y in holes[:, :2]), r, plate_albedo, hole_albedo
        )
        if light is not None:
            albedo = LitAlbedo(albedo, light)
        mesh = _box(np.asarray(placement.centre), placement.size, 10.0)
        objects.append(SceneObject(f"plate-{placement.plate}", mesh, albedo))
        if columns:
            back = placement.centre[2] + 10.0
            for i, xy in enumerate(placement.columns()):
                objects.append(SceneObject(
                    f"column-{placement.plate}-{i}", _column(xy, back, BASE_Z),
                    LitAlbedo(plate_albedo, light) if light is not None else plate_albedo,
                ))
    if base:
        mounts: tuple[tuple[float, float], ...] = ()
        if mount_holes:
            # every column position any configuration uses; the used ones are under columns
            mounts = tuple(
                (float(x), float(y))
                for k in range(len(CONFIGURATIONS))
                for p in plate_placements(k)
                for x, y in p.columns()
            )
        base_reflectance: float | Callable[[np.ndarray], np.ndarray] = base_albedo
        if light is not None or mottling or mounts:
            base_reflectance = LitAlbedo(base_albedo, light, mottling, tuple(sorted(set(mounts))))
        objects.append(
            SceneObject(
                "base", _box(np.array([0.0, 0.0, BASE_Z]), (900.0, 900.0), 40.0),
                base_reflectance,
            )
        )
    points = control_points(configuration, layout=layout_mm)
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
            "hole_layout_mm": layout_mm.tolist(),
            "plate_albedo": plate_albedo,
            "hole_albedo": hole_albedo,
            "base_albedo": base_albedo,
            "columns": bool(columns),
            "mount_holes": bool(mount_holes),
            "mottling": float(mottling),
            "light": None if light is None else asdict(light),
            "control_points": [asdict(p) for p in points],
        },
    )
