"""What a clinic's camera sees: the back with head, hair, neck, arms in several postures and
the waistband of the clothing.

:mod:`rasterserver.simulator.back` builds the trunk (neck to buttocks) and two hanging arms;
this module completes the scene where real rasterstereographs are hard to number:

* the **head** (a slightly flattened ellipsoid on the neck, tilted forwards or backwards),
  whose occiput overhangs the nape and casts a shadow on it; covered by **hair**: dark, low
  and uneven albedo (random fine strands and clumps, so the intensity ratio of two
  neighbouring raster lines says little about their widths there); long hair also covers
  the nape;
* the **arms** in one of three postures: hanging close to the trunk (gap 0-8 mm), held away
  from it (abducted 12-40°), or hands on the hips (elbows out, forearms down to the iliac
  crests); arms cast shadows on the flanks;
* **clothing**: a waistband below the lumbar dimples, a cloth surface standing a few mm off
  the skin with its own albedo, so the raster lines step at its edge;
* **posture sway**: each random scene leans, turns and shifts a little
  (:func:`rasterserver.simulator.back.posture_sway`).

Per-pixel ground truth is the renderer's (``Rendering.line_number``, ``object_index`` with
the object names ``trunk``, ``left-arm``, ``right-arm``, ``head``, ``clothing``).

:func:`clinic_station` is a station that sees the whole scene (taller field of view than the
default station, random working distance and base) with any raster diapositive.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import open3d as o3d

from rasterserver.errors import InputError
from rasterserver.optics import Station, default_station
from rasterserver.raster import Raster
from rasterserver.simulator.back import (
    BackParameters,
    SkinAlbedo,
    _Anatomy,
    _anatomy,
    _mesh,
    _posture_matrix,
    _smooth_polyline,
    _trunk_points,
    _tube,
    make_back,
    posture_sway,
    random_back,
)
from rasterserver.simulator.scene import Scene, SceneObject

__all__ = [
    "ARM_POSTURES",
    "BodyParameters",
    "ClothedSkinAlbedo",
    "HairAlbedo",
    "clinic_station",
    "make_body",
    "random_body",
]

ArmPosture = Literal["close", "away", "hips"]
#: The arm postures of :class:`BodyParameters`.
ARM_POSTURES: tuple[str, ...] = ("close", "away", "hips")


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise InputError(message)


@dataclass(frozen=True)
class BodyParameters:
    """The back plus head, hair, arm posture and clothing; frozen and JSON-serialisable.

    Attributes
    ----------
    back : BackParameters
        Trunk shape, scoliosis, posture and skin (``arm_gap`` is used by the ``"close"``
        posture only).
    arm_posture : {"close", "away", "hips"}
        Arms hanging beside the trunk, held away from it, or hands on the hips.
    arm_abduction : float
        Angle of the arms from the vertical for ``"away"``, degrees, in [0, 60].
    head : bool
        Whether the head is there.
    head_size : float
        Half-height of the head ellipsoid, mm, in [80, 130] (half-width 0.72, half-depth
        0.9 of it).
    head_tilt : float
        Flexion of the head about a horizontal axis through the top of the neck, degrees,
        in [-25, 25]; positive bows the head (the occiput moves up and back).
    occiput_overhang : float
        How far the back of the head stands behind the nape, mm, in [0, 60].
    hair_albedo : float
        Mean hair albedo, in (0, 0.5].
    hair_unevenness : float
        Standard deviation of the log hair albedo (strands and clumps), in [0, 1.2].
    hair_length : float
        How far hair hangs below the occiput onto the nape, mm, in [0, 150].
    hair_seed : int
        Seed of the hair texture.
    waistband : float or None
        Height of the clothing's upper edge as a trunk fraction (1 = DM), in [0.9, 1.6];
        None for no clothing.
    cloth_albedo : float
        Albedo of the cloth, in (0, 1].
    cloth_thickness : float
        How far the cloth stands off the skin, mm, in [0.5, 15].
    """

    back: BackParameters = dataclasses.field(default_factory=BackParameters)
    arm_posture: ArmPosture = "close"
    arm_abduction: float = 25.0
    head: bool = True
    head_size: float = 105.0
    head_tilt: float = 0.0
    occiput_overhang: float = 25.0
    hair_albedo: float = 0.12
    hair_unevenness: float = 0.5
    hair_length: float = 30.0
    hair_seed: int = 0
    waistband: float | None = 1.2
    cloth_albedo: float = 0.3
    cloth_thickness: float = 4.0

    def __post_init__(self) -> None:
        back = self.back
        if not isinstance(back, BackParameters):
            back = BackParameters.from_dict(dict(back))
            object.__setattr__(self, "back", back)
        _check(
            self.arm_posture in ARM_POSTURES,
            f"arm_posture must be one of {list(ARM_POSTURES)}, got {self.arm_posture!r}",
        )
        for name, lo, hi in (
            ("arm_abduction", 0.0, 60.0),
            ("head_size", 80.0, 130.0),
            ("head_tilt", -25.0, 25.0),
            ("occiput_overhang", 0.0, 60.0),
            ("hair_unevenness", 0.0, 1.2),
            ("hair_length", 0.0, 150.0),
            ("cloth_thickness", 0.5, 15.0),
        ):
            value = float(getattr(self, name))
            _check(math.isfinite(value), f"{name} must be finite, got {value!r}")
            _check(lo <= value <= hi, f"{name} must lie in [{lo:g}, {hi:g}], got {value:g}")
            object.__setattr__(self, name, value)
        _check(
            0.0 < self.hair_albedo <= 0.5,
            f"hair_albedo must lie in (0, 0.5], got {self.hair_albedo}",
        )
        _check(
            0.0 < self.cloth_albedo <= 1.0,
            f"cloth_albedo must lie in (0, 1], got {self.cloth_albedo}",
        )
        if self.waistband is not None:
            w = float(self.waistband)
            _check(
                math.isfinite(w) and 0.9 <= w <= 1.6, f"waistband must lie in [0.9, 1.6], got {w}"
            )
            object.__setattr__(self, "waistband", w)
        _check(
            isinstance(self.hair_seed, int | np.integer) and self.hair_seed >= 0,
            f"hair_seed must be an integer >= 0, got {self.hair_seed!r}",
        )
        object.__setattr__(self, "hair_seed", int(self.hair_seed))
        object.__setattr__(self, "head", bool(self.head))

    def to_dict(self) -> dict[str, Any]:
        """The parameters as plain JSON types."""
        out = dataclasses.asdict(self)
        out["back"] = self.back.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> BodyParameters:
        """Inverse of :meth:`to_dict`; unknown keys raise InputError."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        _check(not unknown, f"unknown body parameters: {sorted(unknown)}")
        values = dict(data)
        if "back" in values:
            values["back"] = BackParameters.from_dict(values["back"])
        return cls(**values)


def random_body(seed: int) -> BodyParameters:
    """A varied clinic scene drawn from ``seed`` (reproducibly).

    The back is :func:`~rasterserver.simulator.back.random_back` swayed by up to ±10 mm and
    ±3° (:func:`~rasterserver.simulator.back.posture_sway`); the arm posture is close, away
    or hands on hips in equal shares; the head is always there, hair from black to fair
    (albedo 0.03-0.3, log-albedo spread 0.2-0.9), three in four scenes have a waistband.

    Parameters
    ----------
    seed : int
        Seed of the draw.

    Returns
    -------
    BodyParameters
    """
    rng = np.random.default_rng([int(seed), 0xB0D7])
    back = random_back(seed)
    posture = str(rng.choice(ARM_POSTURES))
    if posture == "close":
        back = dataclasses.replace(back, arm_gap=float(rng.uniform(0.0, 8.0)))
    back = posture_sway(back, seed, translation=10.0, rotation=3.0)
    return BodyParameters(
        back=back,
        arm_posture=posture,  # type: ignore[arg-type]
        arm_abduction=float(rng.uniform(12.0, 40.0)),
        head=True,
        head_size=float(rng.uniform(95.0, 118.0)),
        head_tilt=float(rng.uniform(-15.0, 20.0)),
        occiput_overhang=float(rng.uniform(5.0, 45.0)),
        hair_albedo=float(np.exp(rng.uniform(np.log(0.03), np.log(0.3)))),
        hair_unevenness=float(rng.uniform(0.2, 0.9)),
        hair_length=float(rng.choice([0.0, rng.uniform(0.0, 60.0), rng.uniform(60.0, 140.0)])),
        hair_seed=int(rng.integers(0, 2**31 - 1)),
        waistband=float(rng.uniform(1.05, 1.4)) if rng.random() < 0.75 else None,
        cloth_albedo=float(rng.uniform(0.05, 0.8)),
        cloth_thickness=float(rng.uniform(1.5, 8.0)),
    )


# --------------------------------------------------------------------------------------------
# Albedo


def _body_frame(points: np.ndarray, rot: tuple[float, ...], pivot: tuple[float, ...]) -> np.ndarray:
    """World points back into the body frame (the inverse of the posture)."""
    r = np.asarray(rot, dtype=np.float64).reshape(3, 3)
    p = np.asarray(pivot, dtype=np.float64)
    return (np.asarray(points, dtype=np.float64).reshape(-1, 3) - p) @ r + p


@dataclass(frozen=True)
class HairAlbedo:
    """Dark, uneven hair: log-normal strands and clumps (picklable, on world points).

    The texture is a sum of random plane waves of 2-25 mm wavelength in the body frame, mostly
    along the strands (vertical) but in all directions, normalised so that the log albedo has
    standard deviation ``unevenness``.

    Attributes
    ----------
    mean : float
        Median albedo.
    unevenness : float
        Standard deviation of the log albedo.
    seed : int
        Texture seed.
    rot, pivot : tuple of float
        The body posture (row-major 3 x 3 rotation and its pivot) the texture moves with.
    """

    mean: float
    unevenness: float
    seed: int
    rot: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    pivot: tuple[float, ...] = (0.0, 0.0, 0.0)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Albedo at world points ``(N, 3)``."""
        p = _body_frame(points, self.rot, self.pivot)
        rng = np.random.default_rng([self.seed, 0x4A12])
        k = 16
        wavelength = np.exp(rng.uniform(np.log(2.0), np.log(25.0), k))
        # strands hang down: the texture varies fastest across them (along x and z)
        direction = rng.normal(0.0, 0.6, k) + rng.choice([0.0, np.pi], k)
        phase = rng.uniform(0.0, 2.0 * np.pi, k)
        kx = 2.0 * np.pi / wavelength * np.cos(direction)
        ky = 2.0 * np.pi / wavelength * np.sin(direction)
        kz = 2.0 * np.pi / wavelength * rng.uniform(-0.7, 0.7, k)
        arg = p[:, :1] * kx + p[:, 1:2] * ky + p[:, 2:3] * kz + phase
        noise = np.sin(arg).sum(1) * math.sqrt(2.0 / k)
        return np.clip(self.mean * np.exp(self.unevenness * noise), 0.0, 1.0)


@dataclass(frozen=True)
class ClothedSkinAlbedo:
    """Skin, with hair hanging over the nape above ``hair_y`` (body-frame y) where
    ``|x - hair_x| < hair_half_width``.

    Attributes
    ----------
    skin : SkinAlbedo
    hair : HairAlbedo
    hair_y : float
        Body-frame y of the lower end of the hair on the nape (-inf: none).
    hair_x, hair_half_width : float
        Lateral centre and half-width of the hair over the nape, mm.
    rot, pivot : tuple of float
        The body posture.
    """

    skin: SkinAlbedo
    hair: HairAlbedo
    hair_y: float
    hair_x: float
    hair_half_width: float
    rot: tuple[float, ...]
    pivot: tuple[float, ...]

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Albedo at world points ``(N, 3)``."""
        out = self.skin(points)
        if not math.isfinite(self.hair_y):
            return out
        p = _body_frame(points, self.rot, self.pivot)
        # the hair's lower edge is ragged (strands of different lengths)
        edge = self.hair_y + 8.0 * np.sin(p[:, 0] * 0.45 + self.hair.seed % 7)
        on = (p[:, 1] < edge) & (np.abs(p[:, 0] - self.hair_x) < self.hair_half_width)
        if np.any(on):
            out = out.copy()
            out[on] = self.hair(points[on])
        return out


# --------------------------------------------------------------------------------------------
# Geometry


def _ellipsoid(
    centre: np.ndarray, axes: np.ndarray, *, step: float = 3.0
) -> o3d.geometry.TriangleMesh:
    """Closed ellipsoid mesh (body frame), roughly ``step`` mm between vertices."""
    n_lat = max(24, int(math.pi * axes.max() / step))
    n_lon = max(48, int(2 * math.pi * axes.max() / step))
    lat = np.linspace(0.0, math.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0.0, 2.0 * math.pi, n_lon, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    unit = np.stack([np.sin(la) * np.cos(lo), -np.cos(la), np.sin(la) * np.sin(lo)], -1)
    verts = (unit * axes + centre).reshape(-1, 3)
    rows, cols = lat.size, lon.size
    idx = np.arange(rows * cols).reshape(rows, cols)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1].ravel(), nxt[:-1].ravel(), idx[1:].ravel(), nxt[1:].ravel()
    tris = [np.stack([a, c, b], 1), np.stack([b, c, d], 1)]
    top, bottom = len(verts), len(verts) + 1
    poles = centre[None, :] + np.array([[0.0, -axes[1], 0.0], [0.0, axes[1], 0.0]])
    verts = np.concatenate([verts, poles])
    tris.append(np.stack([np.full(cols, top), idx[0], nxt[0]], 1))
    tris.append(np.stack([np.full(cols, bottom), nxt[-1], idx[-1]], 1))
    triangles = np.concatenate(tris)
    mesh = _mesh(verts, triangles)
    normals = np.asarray(mesh.vertex_normals)
    if ((np.asarray(mesh.vertices) - centre) * normals).sum() < 0:
        mesh = _mesh(verts, triangles[:, ::-1])
    return mesh


def _head(anatomy: _Anatomy, body: BodyParameters) -> tuple[o3d.geometry.TriangleMesh, float]:
    """Head mesh in the body frame, and the body-frame y of the occiput's lower edge."""
    s = anatomy.scale
    half_h = body.head_size
    axes = np.array([0.72 * half_h, half_h, 0.9 * half_h])
    # the occiput's lower edge ~0.25 trunk lengths above C7; the nape there
    t_base = -0.2 - 0.05 * s
    nape = _trunk_points(anatomy, np.zeros(1), np.full(1, t_base))[0]
    centre = np.array(
        [
            nape[0],
            nape[1] - 0.55 * half_h,
            nape[2] - body.occiput_overhang + axes[2],
        ]
    )
    mesh = _ellipsoid(centre, axes)
    # flexion about a horizontal axis through the top of the neck (the atlas)
    a = math.radians(body.head_tilt)
    c, si = math.cos(a), math.sin(a)
    rot = np.array([[1.0, 0.0, 0.0], [0.0, c, si], [0.0, -si, c]])
    pivot = np.array([centre[0], centre[1] + 0.3 * half_h, centre[2]])
    mesh.rotate(rot.T, center=pivot)
    verts = np.asarray(mesh.vertices)
    back_side = verts[:, 2] < centre[2]
    y_low = float(np.percentile(verts[back_side, 1], 97)) if np.any(back_side) else centre[1]
    return mesh, y_low


def _arm_tube(
    anatomy: _Anatomy, side: float, knots: np.ndarray, radii: np.ndarray
) -> o3d.geometry.TriangleMesh:
    """An arm along a polyline of knots, with radii interpolated along its length."""
    centre = _smooth_polyline(knots, step=2.0, sigma=20.0)
    seg = np.linalg.norm(np.diff(knots, axis=0), axis=1)
    knot_arc = np.concatenate([[0.0], np.cumsum(seg)])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centre, axis=0), axis=1))])
    radius = np.interp(arc * knot_arc[-1] / max(arc[-1], 1e-9), knot_arc, radii)
    around = int(max(48, round(2 * np.pi * radii.max() / 2.0)))
    return _tube(centre, radius, around=around)


def _posed_arms(
    anatomy: _Anatomy, body: BodyParameters
) -> tuple[o3d.geometry.TriangleMesh, o3d.geometry.TriangleMesh]:
    """Left and right arm in the body frame for the ``away`` and ``hips`` postures."""
    s = anatomy.scale
    r_sh, r_el, r_wr, r_hand = 46.0 * s, 36.0 * s, 27.0 * s, 26.0 * s
    meshes = []
    for side in (-1.0, 1.0):
        t_sh = 0.12
        ext = _trunk_points(anatomy, np.full(1, side * math.pi / 2), np.full(1, t_sh))[0]
        sh = np.array([ext[0] - side * 0.35 * r_sh, ext[1], ext[2] - 5.0 * s])
        if body.arm_posture == "away":
            a = math.radians(body.arm_abduction)
            d1 = np.array([side * math.sin(a), math.cos(a), 0.08])
            a2 = a + math.radians(8.0)
            d2 = np.array([side * math.sin(a2), math.cos(a2), 0.25])
            el = sh + 290.0 * s * d1 / np.linalg.norm(d1)
            wr = el + 250.0 * s * d2 / np.linalg.norm(d2)
            end = wr + 90.0 * s * d2 / np.linalg.norm(d2)
            knots = np.array([sh, el, wr, end])
            radii = np.array([r_sh, r_el, r_wr, r_hand])
        else:  # hands on the hips: elbows out and a little back, hands on the iliac crests
            t_el, t_wr = 0.55, 0.93
            el = np.array([sh[0] + side * 140.0 * s, anatomy.y_of(t_el), sh[2] - 25.0 * s])
            hip = _trunk_points(anatomy, np.full(1, side * math.pi / 2), np.full(1, t_wr))[0]
            wr = np.array([hip[0] + side * (r_wr + 8.0 * s), hip[1], hip[2] - 10.0 * s])
            end = np.array([hip[0] + side * 10.0 * s, hip[1] + 30.0 * s, hip[2] + 60.0 * s])
            knots = np.array([sh, el, wr, end])
            radii = np.array([r_sh, r_el, r_wr, r_hand])
        meshes.append(_arm_tube(anatomy, side, knots, radii))
    return meshes[0], meshes[1]


def _clothing(
    trunk: o3d.geometry.TriangleMesh,
    anatomy: _Anatomy,
    body: BodyParameters,
    rot: np.ndarray,
    pivot: np.ndarray,
) -> o3d.geometry.TriangleMesh | None:
    """The cloth below the waistband: the trunk's triangles there, moved off the skin."""
    assert body.waistband is not None
    verts = np.asarray(trunk.vertices)
    normals = np.asarray(trunk.vertex_normals)
    local = (verts - pivot) @ rot + pivot
    # a waistband is not quite level: a gentle dip at the back, tilted a little
    y_edge = anatomy.y_of(body.waistband) + 6.0 * np.cos(local[:, 0] / 120.0)
    below = local[:, 1] >= y_edge
    tris = np.asarray(trunk.triangles)
    keep = below[tris].all(axis=1)
    if keep.sum() < 16:
        return None
    # orient the normals outwards: at the spine they face the camera (-Z)
    centre_col = np.abs(local[:, 0] - anatomy.params.offset_x) < 20.0
    sign = -1.0 if (normals[centre_col, 2].mean() if np.any(centre_col) else -1.0) > 0 else 1.0
    moved = verts + sign * body.cloth_thickness * normals
    used = np.unique(tris[keep])
    remap = np.full(verts.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return _mesh(moved[used], remap[tris[keep]])


def make_body(params: BodyParameters, *, spacing: float = 2.0) -> Scene:
    """Build a clinic scene: trunk with neck, head with hair, posed arms, clothing.

    Parameters
    ----------
    params : BodyParameters
        The scene's parameters.
    spacing : float, optional
        Trunk mesh spacing, mm (see :func:`~rasterserver.simulator.back.make_back`).

    Returns
    -------
    Scene
        Objects ``"trunk"``, ``"left-arm"``, ``"right-arm"`` and, when present, ``"head"``
        and ``"clothing"``; the back's landmarks; metadata ``kind`` ``"body"``, the back's
        metadata and ``body`` (these parameters).
    """
    back = params.back
    anatomy = _anatomy(back)
    # the trunk mesh reaches from inside the head (the top of the neck) to below the
    # buttocks, so the camera sees a continuous neck under the head
    y_top = float(anatomy.y_of(-0.2 - 0.05 * anatomy.scale)) - 0.45 * params.head_size
    if not params.head:
        y_top = float(anatomy.y_of(-0.35))
    scene = make_back(back, spacing=spacing, y_range=(y_top, float(anatomy.y_of(1.75))))
    rot, pivot = _posture_matrix(back)
    rot_t = tuple(float(v) for v in rot.ravel())
    pivot_t = tuple(float(v) for v in pivot)
    objects = {o.name: o for o in scene.objects}
    skin = objects["trunk"].albedo
    assert isinstance(skin, SkinAlbedo)
    hair = HairAlbedo(params.hair_albedo, params.hair_unevenness, params.hair_seed, rot_t, pivot_t)
    out: list[SceneObject] = []
    head_low = -math.inf
    if params.head:
        head_mesh, head_low = _head(anatomy, params)
        head_mesh.rotate(rot, center=pivot)
        head_mesh.compute_vertex_normals()
        out.append(SceneObject("head", head_mesh, hair))
    hair_y = head_low + params.hair_length if params.head and params.hair_length > 0 else -math.inf
    nape = _trunk_points(anatomy, np.zeros(1), np.full(1, -0.2))[0]
    trunk_albedo = ClothedSkinAlbedo(
        skin, hair, float(hair_y), float(nape[0]), 75.0 * anatomy.scale, rot_t, pivot_t
    )
    out.append(SceneObject("trunk", objects["trunk"].mesh, trunk_albedo))
    if params.arm_posture == "close":
        out += [objects["left-arm"], objects["right-arm"]]
    else:
        left, right = _posed_arms(anatomy, params)
        for name, mesh in (("left-arm", left), ("right-arm", right)):
            mesh.rotate(rot, center=pivot)
            mesh.compute_vertex_normals()
            out.append(SceneObject(name, mesh, skin))
    if params.waistband is not None:
        cloth = _clothing(objects["trunk"].mesh, anatomy, params, rot, pivot)
        if cloth is not None:
            cloth.compute_vertex_normals()
            out.append(SceneObject("clothing", cloth, params.cloth_albedo))
    metadata = dict(scene.metadata)
    metadata["kind"] = "body"
    metadata["body"] = params.to_dict()
    if params.arm_posture != "close":
        metadata["arm_gap_mm"] = {"left": math.nan, "right": math.nan}
    return Scene(objects=out, landmarks=scene.landmarks, metadata=metadata)


def clinic_station(
    seed: int,
    raster: Raster | str = "default",
    *,
    width: int = 640,
    height: int = 800,
) -> Station:
    """A station that sees head, trunk and buttocks: random working distance and base.

    The default station's optics with a taller sensor and a shorter lens (about 1.1 mm per
    pixel at 2 m, so a ~900 mm tall field of view), working distance 1.85-2.25 m and stereo
    base 0.7-0.85 m drawn from ``seed``.

    Parameters
    ----------
    seed : int
        Seed of the draw.
    raster : Raster or str
        The diapositive (or a built-in name).
    width, height : int
        Sensor size in pixels.

    Returns
    -------
    Station
    """
    rng = np.random.default_rng([int(seed), 0x57A7])
    distance = float(rng.uniform(1850.0, 2250.0))
    return default_station(
        width,
        height,
        distance=distance,
        base=float(rng.uniform(700.0, 850.0)),
        focal_mm=16.0,
        pixel_pitch_mm=0.0088,
        projector_focal=distance,
        raster=raster,
        name=f"clinic-{int(seed)}",
    )
