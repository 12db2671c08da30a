"""A parametric human back, as a rasterstereographic camera sees it from behind.

The model is built for realism where the reconstruction is hard, and for exact ground truth:

* the **trunk** is one smooth parametric surface: at every height a superellipse cross-section
  (flat across the back, rounding into the flanks and wrapping past the widest point, so the
  silhouette is a true contour), whose half-width and depth follow the body outline (neck,
  sloping shoulders, chest, waist, hips). Posterior relief is added on top: the midline furrow
  between the erector muscles, the vertebra prominens (C7), the shoulder blades (raised plates
  with steep medial and inferior flanks), the two lumbar dimples over the posterior superior
  iliac spines, the sacral plateau and the buttocks with the gluteal cleft;
* the **sagittal profile** has a thoracic kyphosis and a lumbar lordosis, the neck leaning
  forward above C7; the whole body can lean forwards or backwards (trunk inclination);
* **scoliosis** is one or more lateral curves of the spinal line, each with an axial rotation
  of the trunk about the spinal line: the cross-section at every height turns about the point
  where the spinal line meets the skin, which lifts the ribs on one side (the rib hump) and
  lowers them on the other;
* the **arms** are separate closed meshes hanging beside the trunk with a gap between them and
  the waist, so raster lines break at the gaps and the arms' depth offsets them;
* the skin **albedo** varies smoothly with a few small naevi, from a seed.

Conventions (world frame of :mod:`rasterserver.simulator.scene`, mm): X to the right as the
camera sees it, which is the patient's right, since the camera looks at the patient's back;
Y down; Z away from the camera, i.e. towards the patient's front, so *posterior* means −Z.
``"left-arm"`` is the patient's left arm, at −X. A positive lateral deviation moves the spinal
line towards +X (a right convex curve); a positive axial rotation turns the +X side backwards
(−Z), so a right thoracic curve with positive deviation and positive rotation has its rib hump
on the right, as in the commonest idiopathic scoliosis.

Heights along the trunk are given as fractions ``t`` of the trunk length: ``t = 0`` at the
vertebra prominens (C7), ``t = 1`` at DM, the point of the spinal line midway between the
lumbar dimples (the landmark ``"dimple_midpoint"``; ``"sacrum"`` is its older name). The
sacrum point SP, the top of the gluteal cleft, lies below DM.

The scene also carries the **truth** the back-shape analysis is measured against (see
:mod:`rasterserver.simulator.back_truth` and ``docs/simulator_truth.md``): the sacrum point, the
inflection points and apices of the sagittal profile of the spinal line, the vertebral-body
centres and the surface normals the parameters need. The patient's **posture** is a rigid
motion of the whole body: the offsets place it, then the sagittal ``inclination``, the frontal
``lateral_lean`` and the ``turn`` about the vertical rotate it (in this order) about axes
through the point ``(0, y_DM, 0)`` of the nominal back plane at the height of DM;
:func:`posture_sway` re-poses a back for repeatability studies.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, overload

import numpy as np
import open3d as o3d
from scipy.interpolate import CubicSpline, PchipInterpolator
from scipy.ndimage import gaussian_filter1d
from scipy.optimize import brentq

from rasterserver.errors import InputError
from rasterserver.simulator.back_truth import body_depth, inclination, sagittal_points
from rasterserver.simulator.scene import Scene, SceneObject

__all__ = [
    "PRESETS",
    "BackParameters",
    "ScoliosisCurve",
    "SkinAlbedo",
    "make_back",
    "posture_sway",
    "preset",
    "random_back",
]

#: Reference shoulder width (mm) the anatomical proportions below are expressed for.
_REFERENCE_SHOULDER_WIDTH = 380.0
#: Fraction of the trunk length between C7 and the top of the image-centred body frame.
_C7_FRACTION = 0.52
#: Lateral distance of each lumbar dimple from the midline, as a fraction of shoulder width.
_DIMPLE_FRACTION = 0.135
#: The gluteal cleft deepens from this height (t) over the next ``_CLEFT_RAMP``.
_CLEFT_TOP = 1.1
_CLEFT_RAMP = 0.15
#: The sacrum point SP (top of the rima ani) is where the cleft reaches this fraction of its
#: full depth.
_SP_DEPTH_FRACTION = 0.1


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise InputError(message)


def _finite(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    _check(math.isfinite(value), f"{name} must be finite, got {value!r}")
    return value


@dataclass(frozen=True)
class ScoliosisCurve:
    """One lateral curve of the spinal line with its axial trunk rotation.

    Both profiles are the compact, twice continuously differentiable bump
    ``(1 - u**2)**3`` with ``u = (t - apex) / extent``, so the deviation and the rotation are
    maximal at the apex and vanish smoothly ``extent`` away from it.

    Attributes
    ----------
    apex : float
        Height of the apex as a fraction of the trunk length (0 = C7, 1 = DM), in [0, 1].
    extent : float
        Half-length of the curve, as a fraction of the trunk length, in [0.05, 1].
    lateral_deviation : float
        Lateral deviation of the spinal line at the apex, mm; positive towards +X (the
        patient's right). At most 120 mm in magnitude.
    rotation : float
        Axial rotation of the trunk about the spinal line at the apex, degrees; positive turns
        the +X side backwards (rib hump on the +X side). At most 60° in magnitude.
    """

    apex: float = 0.35
    extent: float = 0.3
    lateral_deviation: float = 0.0
    rotation: float = 0.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, _finite(f.name, getattr(self, f.name)))
        _check(0.0 <= self.apex <= 1.0, f"apex must lie in [0, 1] (C7..DM), got {self.apex}")
        _check(0.05 <= self.extent <= 1.0, f"extent must lie in [0.05, 1], got {self.extent}")
        _check(
            abs(self.lateral_deviation) <= 120.0,
            f"|lateral_deviation| must be at most 120 mm, got {self.lateral_deviation}",
        )
        _check(abs(self.rotation) <= 60.0, f"|rotation| must be at most 60°, got {self.rotation}")

    def profile(self, t: np.ndarray) -> np.ndarray:
        """Return the unit bump of this curve at trunk heights ``t`` (1 at the apex)."""
        u = (np.asarray(t, dtype=float) - self.apex) / self.extent
        return np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 3, 0.0)


@dataclass(frozen=True)
class BackParameters:
    """Everything that shapes a simulated back; frozen and JSON-serialisable.

    Attributes
    ----------
    trunk_length : float
        Distance from the vertebra prominens (C7) to the sacrum point between the lumbar
        dimples (DM), mm, in [300, 650]. Typical adults 400–520.
    shoulder_width : float
        Breadth of the trunk across the acromions, mm, in [250, 520]; the other breadths and
        depths (neck, chest, waist, hips, arms) scale with it.
    inclination : float
        Sagittal trunk inclination, degrees, in [-25, 25]; positive leans the upper body
        forwards (away from the camera, +Z), about a horizontal axis through DM.
    lateral_lean : float
        Frontal lean of the whole body, degrees, in [-15, 15]; positive leans the upper body
        towards +X (the patient's right), about the axis along Z through ``(0, y_DM, 0)``.
    turn : float
        Rotation of the whole body about the vertical through ``(0, y_DM, 0)``, degrees, in
        [-30, 30]; positive turns the +X side backwards (towards the camera, −Z), the sense of
        a positive axial rotation.
    kyphosis : float
        Depth of the thoracic kyphosis (posterior convexity), mm, in [0, 80].
    lordosis : float
        Depth of the lumbar lordosis (posterior concavity), mm, in [0, 60].
    curves : tuple of ScoliosisCurve
        Scoliotic curves (empty for a straight spine), at most 3.
    scapula_prominence : float
        Height of the shoulder blades over the surrounding back, mm, in [0, 30].
    groove_depth : float
        Depth of the thoracic midline furrow, mm, in [0, 20]; the lumbar furrow between the
        erector muscles is about twice as deep.
    dimple_depth : float
        Depth of the lumbar dimples, mm, in [0, 20].
    buttock_prominence : float
        Posterior bulge of the buttocks over the sacral plane, mm, in [0, 80].
    arm_gap : float
        Smallest horizontal gap between each arm and the trunk below the armpits, mm, in
        [0, 100].
    offset_x, offset_y, offset_z : float
        Where the patient stands relative to the nominal position (C7 and DM centred on the
        optical axis on the back plane Z = 0), mm, each at most 150 in magnitude.
    albedo : float
        Mean skin albedo, in (0, 1].
    albedo_variation : float
        Relative amplitude of the smooth skin albedo variation, in [0, 0.5].
    albedo_seed : int
        Seed of the skin texture (variation and naevi).
    naevi : int
        Number of small dark skin spots (moles), in [0, 100].
    """

    trunk_length: float = 440.0
    shoulder_width: float = 380.0
    inclination: float = 2.0
    lateral_lean: float = 0.0
    turn: float = 0.0
    kyphosis: float = 25.0
    lordosis: float = 15.0
    curves: tuple[ScoliosisCurve, ...] = field(default_factory=tuple)
    scapula_prominence: float = 10.0
    groove_depth: float = 4.0
    dimple_depth: float = 5.0
    buttock_prominence: float = 35.0
    arm_gap: float = 20.0
    offset_x: float = 0.0
    offset_y: float = 0.0
    offset_z: float = 0.0
    albedo: float = 0.55
    albedo_variation: float = 0.08
    albedo_seed: int = 0
    naevi: int = 6

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if f.name in ("curves", "albedo_seed", "naevi"):
                continue
            object.__setattr__(self, f.name, _finite(f.name, getattr(self, f.name)))
        curves = tuple(
            c if isinstance(c, ScoliosisCurve) else ScoliosisCurve(**dict(c)) for c in self.curves
        )
        object.__setattr__(self, "curves", curves)
        ranges = {
            "trunk_length": (300.0, 650.0),
            "shoulder_width": (250.0, 520.0),
            "inclination": (-25.0, 25.0),
            "lateral_lean": (-15.0, 15.0),
            "turn": (-30.0, 30.0),
            "kyphosis": (0.0, 80.0),
            "lordosis": (0.0, 60.0),
            "scapula_prominence": (0.0, 30.0),
            "groove_depth": (0.0, 20.0),
            "dimple_depth": (0.0, 20.0),
            "buttock_prominence": (0.0, 80.0),
            "arm_gap": (0.0, 100.0),
            "offset_x": (-150.0, 150.0),
            "offset_y": (-150.0, 150.0),
            "offset_z": (-150.0, 150.0),
            "albedo_variation": (0.0, 0.5),
        }
        for name, (lo, hi) in ranges.items():
            value = getattr(self, name)
            _check(lo <= value <= hi, f"{name} must lie in [{lo:g}, {hi:g}], got {value:g}")
        _check(0.0 < self.albedo <= 1.0, f"albedo must lie in (0, 1], got {self.albedo:g}")
        _check(len(self.curves) <= 3, f"at most 3 scoliotic curves, got {len(self.curves)}")
        for name in ("albedo_seed", "naevi"):
            value = getattr(self, name)
            _check(
                isinstance(value, int | np.integer) and not isinstance(value, bool),
                f"{name} must be an integer, got {value!r}",
            )
            object.__setattr__(self, name, int(value))
        _check(self.albedo_seed >= 0, f"albedo_seed must be >= 0, got {self.albedo_seed}")
        _check(0 <= self.naevi <= 100, f"naevi must lie in [0, 100], got {self.naevi}")

    def to_dict(self) -> dict[str, Any]:
        """Return the parameters as plain JSON types (curves as a list of dicts)."""
        return dataclasses.asdict(self) | {"curves": [dataclasses.asdict(c) for c in self.curves]}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> BackParameters:
        """Build parameters from :meth:`to_dict` output; unknown keys raise InputError."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        _check(not unknown, f"unknown back parameters: {sorted(unknown)}")
        values = dict(data)
        values["curves"] = tuple(ScoliosisCurve(**dict(c)) for c in values.get("curves", ()))
        return cls(**values)

    def with_primary_curve(
        self, *, lateral_deviation: float | None = None, rotation: float | None = None
    ) -> BackParameters:
        """Return a copy whose first curve has the given deviation and/or rotation.

        A straight back gains a right thoracic curve (apex 0.35, extent 0.3) to carry them.
        """
        curves = list(self.curves) or [ScoliosisCurve()]
        changes: dict[str, float] = {}
        if lateral_deviation is not None:
            changes["lateral_deviation"] = lateral_deviation
        if rotation is not None:
            changes["rotation"] = rotation
        curves[0] = dataclasses.replace(curves[0], **changes)
        return dataclasses.replace(self, curves=tuple(curves))


#: The named backs: a healthy adult, a moderate and a severe idiopathic scoliosis.
PRESETS: dict[str, BackParameters] = {
    "normal": BackParameters(),
    # Right thoracic curve, small lumbar counter-curve: a typical Cobb ~25° adolescent.
    "moderate": BackParameters(
        trunk_length=430.0,
        shoulder_width=360.0,
        kyphosis=20.0,
        curves=(
            ScoliosisCurve(apex=0.35, extent=0.32, lateral_deviation=15.0, rotation=8.0),
            ScoliosisCurve(apex=0.82, extent=0.2, lateral_deviation=-5.0, rotation=-3.0),
        ),
        albedo_seed=1,
    ),
    # Double major curve with a marked rib hump and a flattened (hypokyphotic) thoracic spine.
    "severe": BackParameters(
        trunk_length=420.0,
        shoulder_width=350.0,
        inclination=4.0,
        kyphosis=12.0,
        lordosis=20.0,
        curves=(
            ScoliosisCurve(apex=0.38, extent=0.34, lateral_deviation=35.0, rotation=16.0),
            ScoliosisCurve(apex=0.84, extent=0.22, lateral_deviation=-20.0, rotation=-9.0),
        ),
        scapula_prominence=14.0,
        albedo_seed=2,
    ),
}


def preset(name: str) -> BackParameters:
    """Return the preset back called ``name`` (``normal``, ``moderate``, ``severe``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise InputError(f"unknown back preset {name!r}; choose from {sorted(PRESETS)}") from None


def random_back(seed: int) -> BackParameters:
    """Return a plausible, varied back drawn from ``seed`` (reproducibly).

    Size, posture, sagittal profile, relief, position, skin and scoliosis all vary: about a
    third of the backs are straight, the rest carry one or two curves of up to 40 mm lateral
    deviation and 20° rotation, the kind of spread a scoliosis clinic sees.

    Parameters
    ----------
    seed : int
        Seed of the draw; the same seed gives the same back.

    Returns
    -------
    BackParameters
    """
    rng = np.random.default_rng([int(seed), 0x5BAC])
    curves: list[ScoliosisCurve] = []
    kind = rng.choice(["straight", "single", "double"], p=[0.3, 0.4, 0.3])
    if kind != "straight":
        sign = 1.0 if rng.random() < 0.8 else -1.0  # right thoracic curves dominate
        dev = float(rng.uniform(3.0, 40.0))
        curves.append(
            ScoliosisCurve(
                apex=float(rng.uniform(0.25, 0.5)),
                extent=float(rng.uniform(0.2, 0.38)),
                lateral_deviation=sign * dev,
                rotation=sign * float(np.clip(dev * rng.uniform(0.3, 0.6), 0.0, 20.0)),
            )
        )
    if kind == "double":
        dev = float(rng.uniform(3.0, 25.0))
        sign = -math.copysign(1.0, curves[0].lateral_deviation)
        curves.append(
            ScoliosisCurve(
                apex=float(rng.uniform(0.75, 0.9)),
                extent=float(rng.uniform(0.15, 0.24)),
                lateral_deviation=sign * dev,
                rotation=sign * float(np.clip(dev * rng.uniform(0.3, 0.6), 0.0, 15.0)),
            )
        )
    return BackParameters(
        trunk_length=float(rng.uniform(400.0, 520.0)),
        shoulder_width=float(rng.uniform(320.0, 420.0)),
        inclination=float(rng.normal(2.0, 3.0)),
        kyphosis=float(rng.uniform(10.0, 40.0)),
        lordosis=float(rng.uniform(8.0, 30.0)),
        curves=tuple(curves),
        scapula_prominence=float(rng.uniform(5.0, 16.0)),
        groove_depth=float(rng.uniform(2.0, 7.0)),
        dimple_depth=float(rng.uniform(2.0, 8.0)),
        buttock_prominence=float(rng.uniform(20.0, 50.0)),
        arm_gap=float(rng.uniform(8.0, 45.0)),
        offset_x=float(rng.normal(0.0, 10.0)),
        offset_y=float(rng.normal(0.0, 10.0)),
        offset_z=float(rng.normal(0.0, 20.0)),
        albedo=float(rng.uniform(0.35, 0.75)),
        albedo_variation=float(rng.uniform(0.02, 0.15)),
        albedo_seed=int(rng.integers(0, 2**31 - 1)),
        naevi=int(rng.integers(0, 20)),
    )


def posture_sway(
    params: BackParameters, seed: int, *, translation: float = 5.0, rotation: float = 1.0
) -> BackParameters:
    """Return the same back standing a little differently: the sway between two acquisitions.

    Each offset moves by a uniform draw in ``[-translation, translation]`` mm, and the
    inclination, lateral lean and turn by uniform draws in ``[-rotation, rotation]`` degrees
    (clipped to their ranges); shape, scoliosis and skin stay. Render the result with another
    noise seed for an independent acquisition of the same patient.

    Parameters
    ----------
    params : BackParameters
        The back.
    seed : int
        Seed of the draw; the same seed gives the same posture.
    translation : float, optional
        Largest shift along each axis, mm (>= 0).
    rotation : float, optional
        Largest change of each posture angle, degrees (>= 0).

    Returns
    -------
    BackParameters
    """
    translation = _finite("translation", translation)
    rotation = _finite("rotation", rotation)
    _check(translation >= 0.0 and rotation >= 0.0, "sway amplitudes must be >= 0")
    rng = np.random.default_rng([int(seed), 0x5A7])
    shift = rng.uniform(-translation, translation, 3)
    turn = rng.uniform(-rotation, rotation, 3)
    limits = {"inclination": 25.0, "lateral_lean": 15.0, "turn": 30.0}
    # float fields of BackParameters; replace() rejects an unknown name at run time
    changes: dict[str, Any] = {
        name: float(np.clip(getattr(params, name) + d, -limits[name], limits[name]))
        for name, d in zip(limits, turn, strict=True)
    }
    for name, d in zip(("offset_x", "offset_y", "offset_z"), shift, strict=True):
        changes[name] = float(np.clip(getattr(params, name) + d, -150.0, 150.0))
    return dataclasses.replace(params, **changes)


# --------------------------------------------------------------------------------------------
# Smooth building blocks


def _smootherstep(u: np.ndarray) -> np.ndarray:
    """Quintic 0→1 ramp on [0, 1], C2 at both ends (so curvature maps show no seams)."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (u * (6.0 * u - 15.0) + 10.0)


class _Profile:
    """A smooth (C2) function of trunk height through (t, value) knots.

    PCHIP keeps it free of overshoot; Gaussian smoothing then a cubic spline through dense
    samples makes it twice differentiable, since kinks in the outline would show up as bands
    in the curvature maps the shape analysis computes.
    """

    def __init__(self, knots: Sequence[tuple[float, float]], *, smooth: float = 0.03) -> None:
        t, v = np.asarray(knots, dtype=float).T
        dense = np.linspace(-1.5, 2.5, 2001)
        values = PchipInterpolator(t, v, extrapolate=False)(np.clip(dense, t[0], t[-1]))
        values = gaussian_filter1d(values, smooth / (dense[1] - dense[0]), mode="nearest")
        self._spline = CubicSpline(dense, values)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        return self._spline(np.clip(t, -1.5, 2.5))


@dataclass(frozen=True)
class _Anatomy:
    """Derived shape functions of one back (all lengths in mm, heights as t)."""

    params: BackParameters
    half_width: _Profile
    half_depth: _Profile
    exponent: _Profile
    z_shift: float

    @property
    def length(self) -> float:
        return self.params.trunk_length

    @property
    def scale(self) -> float:
        return self.params.shoulder_width / _REFERENCE_SHOULDER_WIDTH

    @property
    def y_c7(self) -> float:
        return self.params.offset_y - _C7_FRACTION * self.params.trunk_length

    @overload
    def y_of(self, t: float) -> float: ...

    @overload
    def y_of(self, t: np.ndarray) -> np.ndarray: ...

    def y_of(self, t: float | np.ndarray) -> float | np.ndarray:
        return self.y_c7 + np.asarray(t) * self.length

    def t_of(self, y: np.ndarray) -> np.ndarray:
        return (np.asarray(y) - self.y_c7) / self.length

    def deviation(self, t: np.ndarray) -> np.ndarray:
        out = np.zeros_like(np.asarray(t, dtype=float))
        for c in self.params.curves:
            out = out + c.lateral_deviation * c.profile(t)
        return out

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """Axial rotation in degrees at trunk heights ``t``."""
        out = np.zeros_like(np.asarray(t, dtype=float))
        for c in self.params.curves:
            out = out + c.rotation * c.profile(t)
        return out

    def sagittal(self, t: np.ndarray) -> np.ndarray:
        """Depth of the cross-section's posterior pole before relief (mm, +Z is anterior)."""
        p, t = self.params, np.asarray(t, dtype=float)
        kyph = -p.kyphosis * _bump((t - 0.32) / 0.45)
        lord = p.lordosis * _bump((t - 0.85) / 0.32)
        # The cervical spine curves forwards above C7; softplus keeps it smooth at C7.
        w = 0.04
        neck = math.tan(math.radians(25.0)) * self.length * w * np.logaddexp(0.0, -t / w)
        neck -= math.tan(math.radians(25.0)) * self.length * w * math.log(2.0)
        # Below DM the sacrum slopes backwards into the buttocks.
        sacrum = -0.12 * self.length * w * np.logaddexp(0.0, (t - 1.05) / w)
        return kyph + lord + neck + sacrum + self.z_shift

    def relief(self, x: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Posterior elevation (mm towards the camera) of the back's relief at body-local
        lateral position ``x`` (mm from the spinal line) and height ``t``."""
        p, s, h = self.params, self.scale, self.length
        y = t * h  # mm below C7
        elev = np.zeros(np.broadcast(x, t).shape)

        # Midline furrow: shallow between the thoracic spinous processes, deeper between the
        # lumbar erector muscles, fading out on the neck and on the sacrum.
        thoracic = _smootherstep((t + 0.05) / 0.12) * (1.0 - _smootherstep((t - 0.6) / 0.2))
        lumbar = _smootherstep((t - 0.5) / 0.2) * (1.0 - _smootherstep((t - 0.95) / 0.12))
        groove = p.groove_depth * (thoracic + 1.6 * lumbar)
        sigma = 9.0 * s + 4.0 * s * lumbar
        elev -= groove * np.exp(-0.5 * (x / sigma) ** 2)
        # Erector spinae: two paravertebral ridges, strongest in the lumbar region.
        ridge = (1.5 + 5.0 * lumbar) * (1.0 - _smootherstep((t - 1.0) / 0.1))
        ridge *= _smootherstep((t + 0.02) / 0.1)
        for side in (-1.0, 1.0):
            elev += ridge * np.exp(-0.5 * ((x - side * 36.0 * s) / (17.0 * s)) ** 2)

        # The vertebra prominens stands out of the furrow.
        elev += 5.0 * np.exp(-0.5 * ((x / (9.0 * s)) ** 2 + (y / 9.0) ** 2))

        # Shoulder blades: triangular plates, steep along the medial border and the inferior
        # angle, blending into the muscles superiorly and laterally.
        if p.scapula_prominence > 0.0:
            for side in (-1.0, 1.0):
                elev += p.scapula_prominence * _scapula(side * x, y, s, h)

        # Lumbar dimples over the posterior superior iliac spines.
        dx = _DIMPLE_FRACTION * p.shoulder_width
        for side in (-1.0, 1.0):
            r2 = (x - side * dx) ** 2 + (y - h) ** 2
            elev -= p.dimple_depth * np.exp(-0.5 * r2 / (9.0 * s) ** 2)

        # Buttocks and the gluteal cleft below the sacrum.
        if p.buttock_prominence > 0.0:
            for side in (-1.0, 1.0):
                u = (x - side * 75.0 * s) / (70.0 * s)
                v = (t - 1.33) / 0.2
                elev += p.buttock_prominence * np.exp(-0.5 * (u * u + v * v))
            cleft = _smootherstep((t - _CLEFT_TOP) / _CLEFT_RAMP) * p.buttock_prominence * 0.5
            elev -= cleft * np.exp(-0.5 * (x / (7.0 * s)) ** 2)
        return elev


def _bump(u: np.ndarray) -> np.ndarray:
    u = np.asarray(u, dtype=float)
    return np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 3, 0.0)


def _scapula(x: np.ndarray, y: np.ndarray, s: float, h: float) -> np.ndarray:
    """Unit elevation of the right shoulder blade at lateral ``x`` and depth-below-C7 ``y``."""
    # Corners (x mm from the spinal line, y mm below C7): superior angle, inferior angle,
    # glenoid (lateral angle); the inferior angle lies near T7.
    sup = np.array([70.0 * s, 0.03 * h])
    inf = np.array([88.0 * s, 0.37 * h])
    lat = np.array([160.0 * s, 0.12 * h])
    # Width (mm) over which each border rises: steep along the medial border and around the
    # inferior angle; the lateral border softens as it runs under the teres muscles and the
    # superior border blends into the trapezius.
    borders = ((sup, inf, 9.0, 9.0), (inf, lat, 10.0, 40.0), (lat, sup, 45.0, 45.0))
    x, y = np.broadcast_arrays(x, y)
    inside = np.ones(x.shape)
    centroid = (sup + inf + lat) / 3.0
    d_medial = np.zeros(x.shape)
    for k, (a, b, w0, w1) in enumerate(borders):
        edge = b - a
        length = float(np.hypot(*edge))
        normal = np.array([-edge[1], edge[0]]) / length
        if np.dot(centroid - a, normal) < 0:
            normal = -normal
        dist = (x - a[0]) * normal[0] + (y - a[1]) * normal[1]
        along = np.clip(((x - a[0]) * edge[0] + (y - a[1]) * edge[1]) / length**2, 0.0, 1.0)
        inside = inside * _smootherstep(dist / (w0 + (w1 - w0) * along))
        if k == 0:
            d_medial = dist
    # Highest along the medial border, sloping gently down laterally like the real plate on
    # the curved rib cage.
    return inside * (0.6 + 0.4 * np.exp(-np.clip(d_medial, 0.0, None) / 40.0))


def _anatomy(params: BackParameters) -> _Anatomy:
    s = params.shoulder_width / _REFERENCE_SHOULDER_WIDTH
    w = params.shoulder_width
    half_width = _Profile(
        [
            (-1.0, 0.155 * w),
            (-0.12, 0.155 * w),  # neck base
            (0.07, 0.5 * w),  # acromion: shoulder width
            (0.27, 0.415 * w),  # below the armpits: chest breadth
            (0.68, 0.34 * w),  # waist
            (1.15, 0.455 * w),  # hips
            (2.0, 0.44 * w),
        ],
        smooth=0.03,
    )
    half_depth = _Profile(
        [
            (-1.0, 55.0 * s),
            (-0.12, 62.0 * s),
            (0.07, 95.0 * s),
            (0.3, 115.0 * s),
            (0.68, 95.0 * s),
            (1.15, 110.0 * s),
            (2.0, 110.0 * s),
        ],
        smooth=0.03,
    )
    exponent = _Profile(
        [(-1.0, 2.0), (-0.12, 2.0), (0.1, 2.4), (0.35, 2.7), (0.68, 2.4), (1.2, 2.5), (2.0, 2.3)],
        smooth=0.05,
    )
    anatomy = _Anatomy(params, half_width, half_depth, exponent, 0.0)
    # Put the nominal back plane (Z = 0) at the mean depth of the spinal line from C7 to DM.
    t = np.linspace(0.0, 1.0, 201)
    z_mid = anatomy.sagittal(t) - anatomy.relief(np.zeros_like(t), t)
    return dataclasses.replace(anatomy, z_shift=float(-z_mid.mean()) + params.offset_z)


# --------------------------------------------------------------------------------------------
# Geometry


def _trunk_points(anatomy: _Anatomy, theta: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Body-frame points (before inclination) at cross-section angle ``theta`` and height ``t``.

    ``theta = 0`` is the spinal line; ``|theta| = pi/2`` the widest point of the section.
    """
    theta, t = np.broadcast_arrays(np.asarray(theta, float), np.asarray(t, float))
    a, b, p = anatomy.half_width(t), anatomy.half_depth(t), anatomy.exponent(t)
    sin, cos = np.sin(theta), np.cos(theta)
    x = a * np.sign(sin) * np.abs(sin) ** (2.0 / p)
    z = anatomy.sagittal(t) + b * (1.0 - np.sign(cos) * np.abs(cos) ** (2.0 / p))
    # Relief is painted on the visible back and faded out towards the flanks, where it
    # would otherwise poke through the silhouette.
    fade = 1.0 - _smootherstep((np.abs(x) / a - 0.82) / 0.16)
    fade = np.where(np.abs(theta) < np.pi / 2, fade, 0.0)
    z = z - anatomy.relief(x, t) * fade
    # Axial rotation about the spinal line (where it meets the skin, theta = 0).
    z_axis = anatomy.sagittal(t) - anatomy.relief(np.zeros_like(t), t)
    phi = np.radians(anatomy.rotation(t))
    c, s = np.cos(phi), np.sin(phi)
    xr = x * c + (z - z_axis) * s
    zr = z_axis - x * s + (z - z_axis) * c
    return np.stack([xr + anatomy.deviation(t) + anatomy.params.offset_x, anatomy.y_of(t), zr], -1)


def _theta_for_x(anatomy: _Anatomy, x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Cross-section angle of body-local lateral position ``x`` (|x| < half-width)."""
    a, p = anatomy.half_width(t), anatomy.exponent(t)
    ratio = np.clip(np.abs(x) / a, 0.0, 1.0)
    return np.sign(x) * np.arcsin(ratio ** (p / 2.0))


def _posture_matrix(params: BackParameters) -> tuple[np.ndarray, np.ndarray]:
    """The posture's rotation (inclination, then lateral lean, then turn) and its pivot."""
    a = math.radians(params.inclination)
    c, s = math.cos(a), math.sin(a)
    # Rows act on (x, y, z): a point above the pivot (y < y_dm) moves to +Z for a > 0.
    rot = np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])
    if params.lateral_lean:
        # About Z: a point above the pivot moves to +X for a positive lean.
        b = math.radians(params.lateral_lean)
        cb, sb = math.cos(b), math.sin(b)
        rot = np.array([[cb, -sb, 0.0], [sb, cb, 0.0], [0.0, 0.0, 1.0]]) @ rot
    if params.turn:
        # About Y: +X moves to -Z (posterior) for a positive turn.
        g = math.radians(params.turn)
        cg, sg = math.cos(g), math.sin(g)
        rot = np.array([[cg, 0.0, sg], [0.0, 1.0, 0.0], [-sg, 0.0, cg]]) @ rot
    # Upright, unturned backs keep the exact matrix they always had (renders reproduce).
    y_dm = params.offset_y + (1.0 - _C7_FRACTION) * params.trunk_length
    return rot, np.array([0.0, y_dm, 0.0])


def _to_world(params: BackParameters, points: np.ndarray) -> np.ndarray:
    rot, pivot = _posture_matrix(params)
    return (points - pivot) @ rot.T + pivot


def _section_points(anatomy: _Anatomy, x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Body-frame skin points at body-local lateral position ``x`` (mm) and height ``t``."""
    return _trunk_points(anatomy, _theta_for_x(anatomy, x, t), t)


def _outward_normals(anatomy: _Anatomy, x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World unit normals of the skin facing the camera (-Z side) at local ``x``, height ``t``."""
    x, t = np.broadcast_arrays(np.asarray(x, float), np.asarray(t, float))
    h, ht = 0.05, 0.05 / anatomy.length  # 0.05 mm either way
    across = _section_points(anatomy, x + h, t) - _section_points(anatomy, x - h, t)
    down = _section_points(anatomy, x, t + ht) - _section_points(anatomy, x, t - ht)
    rot, _ = _posture_matrix(anatomy.params)
    n = np.cross(down, across) @ rot.T
    n *= np.where(n[..., 2:] > 0.0, -1.0, 1.0)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _sacrum_point_t() -> float:
    """Height (t) of the sacrum point: the cleft at ``_SP_DEPTH_FRACTION`` of its depth."""
    u = brentq(lambda v: float(_smootherstep(np.asarray(v))) - _SP_DEPTH_FRACTION, 0.0, 1.0)
    return _CLEFT_TOP + _CLEFT_RAMP * u


def _truth(anatomy: _Anatomy, t_mid: np.ndarray) -> tuple[dict[str, Any], dict[str, Any]]:
    """Landmarks and metadata of the analysis's truth (see :mod:`.back_truth`)."""
    params = anatomy.params
    zero = np.zeros_like(t_mid)
    # Vertebral-body centres: in front of the spinal line's skin point, along the section's
    # sagittal direction turned by the axial rotation about that point (as the trunk is).
    skin = _trunk_points(anatomy, zero, t_mid)
    depth = body_depth(t_mid, params.trunk_length)
    phi = np.radians(anatomy.rotation(t_mid))
    bodies = skin + np.stack([depth * np.sin(phi), zero, depth * np.cos(phi)], -1)
    # The sagittal profile, sampled beyond VP and DM every 0.5 mm or less so that the
    # tangents at VP and DM are central differences too; t = 0 and 1 are samples.
    k = math.ceil(0.1 * params.trunk_length / 0.5)
    t_ext = np.arange(-k, 11 * k + 1) / (10.0 * k)
    profile = _to_world(params, _trunk_points(anatomy, np.zeros_like(t_ext), t_ext))
    alpha = inclination(profile[:, 1], profile[:, 2])
    idx = sagittal_points(t_ext, profile[:, 1], profile[:, 2])
    t_sp = _sacrum_point_t()
    sp = _to_world(params, _trunk_points(anatomy, np.zeros(1), np.full(1, t_sp)))[0]
    normals = _outward_normals(anatomy, zero, t_mid)
    dx = _DIMPLE_FRACTION * params.shoulder_width
    dimple_normals = _outward_normals(anatomy, np.array([-dx, dx]), np.ones(2))
    landmarks: dict[str, Any] = {
        "sacrum_point": sp,
        "vertebral_bodies": _to_world(params, bodies),
        **{f"sagittal_{name}": profile[i].copy() for name, i in idx.items()},
    }
    spine = {
        "body_depth_mm": depth.tolist(),
        "surface_rotation_deg": np.degrees(np.arctan2(-normals[:, 0], -normals[:, 2])).tolist(),
        "sagittal_inclination_deg": np.interp(t_mid, t_ext, alpha).tolist(),
    }
    truth = {
        "sacrum_point_t": t_sp,
        "sagittal": {
            name: {"t": float(t_ext[i]), "inclination_deg": float(alpha[i])}
            for name, i in idx.items()
        },
        "dimple_normals": {
            "left": dimple_normals[0].tolist(),
            "right": dimple_normals[1].tolist(),
        },
    }
    return landmarks, {"spine": spine, "truth": truth}


def _grid_triangles(rows: int, cols: int) -> np.ndarray:
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])


def _mesh(vertices: np.ndarray, triangles: np.ndarray) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.ascontiguousarray(vertices, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.ascontiguousarray(triangles, dtype=np.int32)),
    )
    mesh.compute_vertex_normals()
    return mesh


def _arc_length_angles(anatomy: _Anatomy, n: int, theta_max: float) -> np.ndarray:
    """Angles spaced evenly in arc length around the chest cross-section."""
    fine = np.linspace(-theta_max, theta_max, 4001)
    pts = _trunk_points(anatomy, fine, np.full_like(fine, 0.4))
    seg = np.hypot(np.diff(pts[:, 0]), np.diff(pts[:, 2]))
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    return np.interp(np.linspace(0.0, arc[-1], n), arc, fine)


def _trunk_mesh(
    anatomy: _Anatomy, *, spacing: float, y_range: tuple[float, float]
) -> tuple[o3d.geometry.TriangleMesh, np.ndarray, np.ndarray]:
    """Trunk mesh in the body frame plus the per-row y and lateral extremes (for the arms)."""
    theta_max = math.radians(105.0)
    ref = _trunk_points(anatomy, np.linspace(-theta_max, theta_max, 2001), np.full(2001, 0.4))
    arc = np.hypot(np.diff(ref[:, 0]), np.diff(ref[:, 2])).sum()
    cols = max(math.ceil(arc / spacing) + 1, 16)
    rows = max(math.ceil((y_range[1] - y_range[0]) / spacing) + 1, 16)
    theta = _arc_length_angles(anatomy, cols, theta_max)
    y = np.linspace(y_range[0], y_range[1], rows)
    tt, th = np.meshgrid(anatomy.t_of(y), theta, indexing="ij")
    pts = _trunk_points(anatomy, th, tt)
    return _mesh(pts.reshape(-1, 3), _grid_triangles(rows, cols)), y, pts


def _tube(centre: np.ndarray, radius: np.ndarray, *, around: int) -> o3d.geometry.TriangleMesh:
    """Closed tube along a polyline (N, 3) with radii (N,), hemispherical-ish end caps."""
    tangent = np.gradient(centre, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    # Cap each end with rings shrinking onto a pole, a quarter circle in profile.
    caps = np.linspace(0.0, np.pi / 2, 10)[1:-1]
    start = [(centre[0] - radius[0] * np.sin(a) * tangent[0], radius[0] * np.cos(a)) for a in caps]
    end = [
        (centre[-1] + radius[-1] * np.sin(a) * tangent[-1], radius[-1] * np.cos(a)) for a in caps
    ]
    centres = np.concatenate(
        [np.array([c for c, _ in start[::-1]]), centre, np.array([c for c, _ in end])]
    )
    radii = np.concatenate([[r for _, r in start[::-1]], radius, [r for _, r in end]])
    tangents = np.concatenate(
        [np.repeat(tangent[:1], len(start), 0), tangent, np.repeat(tangent[-1:], len(end), 0)]
    )
    ref = np.array([0.0, 0.0, 1.0])
    u = np.cross(tangents, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(tangents, u)
    ang = np.linspace(0.0, 2.0 * np.pi, around, endpoint=False)
    ring = centres[:, None, :] + radii[:, None, None] * (
        np.cos(ang)[None, :, None] * u[:, None, :] + np.sin(ang)[None, :, None] * v[:, None, :]
    )
    n_rings = len(centres)
    verts = ring.reshape(-1, 3)
    idx = np.arange(n_rings * around).reshape(n_rings, around)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1].ravel(), nxt[:-1].ravel(), idx[1:].ravel(), nxt[1:].ravel()
    tris = [np.stack([a, b, c], 1), np.stack([b, d, c], 1)]
    pole0 = centre[0] - radius[0] * tangent[0]
    pole1 = centre[-1] + radius[-1] * tangent[-1]
    i0, i1 = len(verts), len(verts) + 1
    verts = np.concatenate([verts, pole0[None], pole1[None]])
    first, last = idx[0], idx[-1]
    tris.append(np.stack([np.full(around, i0), np.roll(first, -1), first], 1))
    tris.append(np.stack([np.full(around, i1), last, np.roll(last, -1)], 1))
    triangles = np.concatenate(tris)
    # Make the normals point outwards whatever the handedness of the ring frame.
    mesh = _mesh(verts, triangles)
    normals = np.asarray(mesh.vertex_normals)[: n_rings * around]
    outward = (ring.reshape(-1, 3) - np.repeat(centres, around, 0)) * normals
    if outward.sum() < 0:
        mesh = _mesh(verts, triangles[:, ::-1])
    return mesh


def _smooth_polyline(knots: np.ndarray, *, step: float, sigma: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(knots, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, arc[-1] + step / 2, step)
    pts = np.stack([np.interp(s, arc, knots[:, k]) for k in range(3)], 1)
    # Round the elbow; keep the ends fixed by smoothing with reflected padding.
    smooth = gaussian_filter1d(pts, sigma / step, axis=0, mode="nearest")
    w = np.clip(np.minimum(s, arc[-1] - s) / (3 * sigma), 0.0, 1.0)[:, None]
    return pts * (1 - w) + smooth * w


def _arm(
    anatomy: _Anatomy,
    side: float,
    rows_y: np.ndarray,
    extreme_x: np.ndarray,
    extreme_z: np.ndarray,
) -> tuple[o3d.geometry.TriangleMesh, float]:
    """One arm (side +1: +X, the patient's right) and its smallest gap to the trunk (mm)."""
    p, s = anatomy.params, anatomy.scale
    y_sh, y_el, y_wr, y_end = (anatomy.y_of(t) for t in (0.18, 0.62, 1.2, 1.65))
    r_sh, r_el, r_wr, r_hand = 46.0 * s, 36.0 * s, 27.0 * s, 26.0 * s
    out = side * extreme_x  # lateral extreme of the trunk per row, positive outwards

    def at(y: float, values: np.ndarray) -> float:
        return float(np.interp(y, rows_y, values))

    # The humeral head sits under the acromion; the deltoid bulges just beyond it.
    x_sh = float(np.interp(anatomy.y_of(0.07), rows_y, out)) - 0.15 * r_sh
    # The arm hangs straight, angled just enough outwards to clear the trunk by the gap
    # everywhere from the lower ribs down (higher up, arm and chest touch, as in a real
    # patient standing relaxed).
    y_gap0 = anatomy.y_of(0.55)
    ys = rows_y[(rows_y >= y_gap0) & (rows_y <= y_end)]
    r_at = np.interp(ys, [y_sh, y_el, y_wr, y_end], [r_sh, r_el * 1.1, r_wr, r_hand])
    need = np.interp(ys, rows_y, out) + p.arm_gap + r_at + 0.5
    slope = float(max(0.0, ((need - x_sh) / (ys - y_sh)).max(initial=0.0)))

    z_sh = at(y_sh, extreme_z) - 10.0 * s
    z_el = at(y_el, extreme_z) + 5.0 * s

    def build(slope: float) -> tuple[np.ndarray, np.ndarray]:
        def x_at(y: float) -> float:
            return x_sh + slope * (y - y_sh)

        # The elbows flex slightly: the forearms hang a little forwards of the upper arms.
        knots = np.array(
            [
                [side * x_sh, y_sh, z_sh],
                [side * x_at(y_el), y_el, z_el],
                [side * x_at(y_wr), y_wr, z_el + 25.0 * s],
                [side * x_at(y_end), y_end, z_el + 35.0 * s],
            ]
        )
        centre = _smooth_polyline(knots, step=2.0, sigma=25.0)
        # Radius along the arm: deltoid, upper arm, elbow, forearm bulge, wrist, hand.
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centre, axis=0), 1))])
        radius = np.interp(
            centre[:, 1],
            [y_sh, y_sh + 0.3 * (y_el - y_sh), y_el, y_el + 0.25 * (y_wr - y_el), y_wr, y_end],
            [r_sh, 0.95 * r_sh, r_el, 1.1 * r_el, r_wr, r_hand],
        )
        radius = gaussian_filter1d(radius, 10.0 / max(along[1] - along[0], 1e-6), mode="nearest")
        return centre, radius

    def gaps(centre: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Horizontal gap below the armpits, at the arm's widest extent per height.
        ys = centre[:, 1]
        sel = (ys >= y_gap0) & (ys <= min(y_end, rows_y[-1]))
        trunk = np.interp(ys[sel], rows_y, out)
        return ys[sel], side * centre[sel, 0] - radius[sel] - trunk

    centre, radius = build(slope)
    # The smoothed elbow and radius profile can eat into the gap a little: steepen the arm
    # until the measured gap holds.
    for _ in range(4):
        ys, gap_y = gaps(centre, radius)
        deficit = p.arm_gap + 0.1 - gap_y
        if gap_y.size == 0 or deficit.max() <= 0.0:
            break
        slope += float((deficit / np.maximum(ys - y_sh, 1.0)).max())
        centre, radius = build(slope)
    mesh = _tube(centre, radius, around=int(max(48, round(2 * np.pi * r_sh / 2.0))))
    gap_y = gaps(centre, radius)[1]
    gap = float(gap_y.min()) if gap_y.size else math.nan
    return mesh, gap


# --------------------------------------------------------------------------------------------
# Skin


@dataclass(frozen=True)
class SkinAlbedo:
    """Skin reflectance: a smooth random variation with a few small dark naevi.

    A picklable callable (so a scene can travel to a worker process), evaluated on world
    points; the texture depends only on X and Y, which is fine for a rigid patient.

    Attributes
    ----------
    mean : float
        Mean albedo.
    variation : float
        Relative amplitude of the smooth variation.
    seed : int
        Seed of the texture.
    naevi : int
        Number of naevi (radius 1.5–3 mm, albedo ~40 % of the skin's).
    """

    mean: float = 0.55
    variation: float = 0.08
    seed: int = 0
    naevi: int = 6

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Return the albedo at world points ``(N, 3)`` as ``(N,)`` in [0, 1]."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        rng = np.random.default_rng([self.seed, 0xA1BED0])
        # A sum of random plane waves with wavelengths 40–250 mm, normalised to unit RMS.
        k = 12
        wavelength = rng.uniform(40.0, 250.0, k)
        direction = rng.uniform(0.0, 2.0 * np.pi, k)
        phase = rng.uniform(0.0, 2.0 * np.pi, k)
        kx = 2.0 * np.pi / wavelength * np.cos(direction)
        ky = 2.0 * np.pi / wavelength * np.sin(direction)
        waves = np.sin(pts[:, :1] * kx + pts[:, 1:2] * ky + phase).sum(1) * math.sqrt(2.0 / k)
        albedo = self.mean * (1.0 + self.variation * waves)
        centres = rng.uniform([-200.0, -250.0], [200.0, 250.0], (self.naevi, 2))
        radii = rng.uniform(1.5, 3.0, self.naevi)
        for (cx, cy), r in zip(centres, radii, strict=True):
            d2 = (pts[:, 0] - cx) ** 2 + (pts[:, 1] - cy) ** 2
            albedo = albedo * (1.0 - 0.6 * np.exp(-0.5 * d2 / (r * 0.6) ** 2))
        return np.clip(albedo, 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# The scene


def make_back(
    params: BackParameters,
    *,
    spacing: float = 1.5,
    y_range: tuple[float, float] = (-340.0, 360.0),
) -> Scene:
    """Build the scene of a back: trunk, left and right arm, landmarks and metadata.

    Parameters
    ----------
    params : BackParameters
        The back's shape, posture, scoliosis and skin.
    spacing : float, optional
        Trunk mesh spacing, mm (in [0.5, 5]); 1.5 mm gives ~300k triangles, and vertex
        normals make the shading smooth between vertices.
    y_range : tuple of float, optional
        Heights (mm, before the trunk inclination) the trunk mesh spans; the default covers
        the default camera's 604 mm tall field of view with a margin.

    Returns
    -------
    Scene
        Objects ``"trunk"``, ``"left-arm"`` (at −X) and ``"right-arm"`` (at +X), all with the
        same :class:`SkinAlbedo`. Landmarks (world mm):

        * ``"vertebra_prominens"`` (VP, C7, on the skin at the top of the spinal line);
        * ``"dimple_left"`` and ``"dimple_right"`` (DL, DR: centres of the lumbar dimples, on
          the skin, at height ``t = 1``);
        * ``"dimple_midpoint"`` (DM: the spinal line's skin point at ``t = 1``, midway between
          the dimples); ``"sacrum"`` is the same point under its older name;
        * ``"sacrum_point"`` (SP: the top of the rima ani, on the skin at the bottom of the
          gluteal cleft, where the cleft reaches a tenth of its full depth, ~0.135 trunk
          lengths below DM);
        * ``"spinal_midline"`` (M, 3): the spinal line on the skin, i.e. the line of the
          spinous processes at the bottom of the midline furrow, about which the trunk
          rotates, from VP to DM at 2 mm steps;
        * ``"vertebral_bodies"`` (M, 3): the vertebral-body centres at the same heights,
          ``body_depth_mm`` in front of the skin along the section's sagittal direction
          turned by the axial rotation (skin + R(rotation)·(0, 0, depth) before the posture);
        * ``"sagittal_ICT"``, ``"sagittal_KA"``, ``"sagittal_ITL"``, ``"sagittal_LA"``,
          ``"sagittal_ILS"``: the inflection points and apices of the sagittal profile of the
          spinal line, on the skin (definitions in :mod:`.back_truth`).

        Metadata: the parameters; under ``"spine"`` per midline point the height fraction
        ``t``, world ``y``, the applied ``lateral_deviation_mm`` and ``axial_rotation_deg``,
        ``body_depth_mm``, the ``surface_rotation_deg`` of the skin normal and the
        ``sagittal_inclination_deg`` of the profile; under ``"truth"`` the heights and
        tangent inclinations of the sagittal points, the sacrum point's ``t`` and the skin
        normals at the dimples; the measured arm gaps. :func:`.back_truth.truth` turns them
        into the analysis's landmarks and parameters.

    Raises
    ------
    InputError
        For a spacing or y range outside the supported values.
    """
    spacing = _finite("spacing", spacing)
    _check(0.5 <= spacing <= 5.0, f"spacing must lie in [0.5, 5] mm, got {spacing:g}")
    y0, y1 = (_finite("y_range", v) for v in y_range)
    _check(y1 - y0 >= 50.0, f"y_range must span at least 50 mm, got {y_range}")

    anatomy = _anatomy(params)
    trunk, rows_y, grid = _trunk_mesh(anatomy, spacing=spacing, y_range=(y0, y1))
    # Arms are placed in the body frame against the trunk's actual outline, row by row.
    right_i = grid[:, :, 0].argmax(axis=1)
    left_i = grid[:, :, 0].argmin(axis=1)
    rows = np.arange(len(rows_y))
    right_x, right_z = grid[rows, right_i, 0], grid[rows, right_i, 2]
    left_x, left_z = grid[rows, left_i, 0], grid[rows, left_i, 2]
    right_arm, gap_right = _arm(anatomy, 1.0, rows_y, right_x, right_z)
    left_arm, gap_left = _arm(anatomy, -1.0, rows_y, left_x, left_z)

    rot, pivot = _posture_matrix(params)
    for mesh in (trunk, right_arm, left_arm):
        mesh.rotate(rot, center=pivot)
        mesh.compute_vertex_normals()

    # Landmarks, from the same mapping as the mesh.
    t_mid = np.linspace(0.0, 1.0, round(params.trunk_length / 2.0) + 1)
    midline = _to_world(params, _trunk_points(anatomy, np.zeros_like(t_mid), t_mid))
    dx = _DIMPLE_FRACTION * params.shoulder_width
    xs = np.array([-dx, dx])
    ts = np.ones(2)
    dimples = _to_world(params, _trunk_points(anatomy, _theta_for_x(anatomy, xs, ts), ts))
    truth_landmarks, truth_metadata = _truth(anatomy, t_mid)
    landmarks = {
        "vertebra_prominens": midline[0].copy(),
        "dimple_midpoint": midline[-1].copy(),
        "sacrum": midline[-1].copy(),
        "dimple_left": dimples[0],
        "dimple_right": dimples[1],
        "spinal_midline": midline,
        **truth_landmarks,
    }
    albedo = SkinAlbedo(params.albedo, params.albedo_variation, params.albedo_seed, params.naevi)
    metadata: dict[str, Any] = {
        "kind": "back",
        "parameters": params.to_dict(),
        "spacing_mm": spacing,
        "spine": {
            "t": t_mid.tolist(),
            "y": midline[:, 1].tolist(),
            "lateral_deviation_mm": anatomy.deviation(t_mid).tolist(),
            "axial_rotation_deg": anatomy.rotation(t_mid).tolist(),
            **truth_metadata["spine"],
        },
        "truth": truth_metadata["truth"],
        "arm_gap_mm": {"left": gap_left, "right": gap_right},
        "conventions": (
            "world mm, X right (patient's right), Y down, Z away from the camera (anterior); "
            "deviation + towards +X; rotation + turns the +X side posterior (-Z); "
            "spinal_midline = spinous-process line on the skin (furrow bottom), C7 to DM; "
            "vertebral_bodies = body centres at body_depth_mm in front of it, turned by the "
            "axial rotation; see rasterserver.simulator.back_truth"
        ),
    }
    return Scene(
        objects=[
            SceneObject("trunk", trunk, albedo),
            SceneObject("left-arm", left_arm, albedo),
            SceneObject("right-arm", right_arm, albedo),
        ],
        landmarks=landmarks,
        metadata=metadata,
    )
