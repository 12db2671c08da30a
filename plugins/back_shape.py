"""The back-shape analysis stage: curvature, landmarks, symmetry line, midline, parameters.

A pure function of the smoothed :class:`~rasterserver.records_surface.Surface` and the
station's vertical (``context.calibration.gravity``), wiring the concepts of their own modules:

1. :mod:`~rasterserver_plugins.level_frame`: the surface in a frame whose ``y'`` axis is
   plumb (profiles are horizontal sections);
2. :mod:`~rasterserver_plugins.curvature`: H, K, κ1, κ2 and principal directions;
3. :mod:`~rasterserver_plugins.trunk`: the measured trunk, its outline and centre;
4. :mod:`~rasterserver_plugins.landmarks`: VP, DL, DR, DM, SP (Drerup & Hierholzer 1987);
   VP checked against the symmetry axis below it (:mod:`~rasterserver_plugins.vp_axis`);
5. :mod:`~rasterserver_plugins.body_frame`: the body-fixed frame from VP, DL, DR;
6. :mod:`~rasterserver_plugins.symmetry_line`: Hierholzer's symmetry line VP → DM;
7. :mod:`~rasterserver_plugins.spinal_midline`: surface rotation and the vertebral-body
   centres (Drerup & Hierholzer 1994);
8. :mod:`~rasterserver_plugins.back_parameters`: the clinical parameters.

Positions are returned in the calibration's world frame; the curvature maps lie on the level
grid (the world grid itself when gravity is the world's +Y, as for the default station),
whose axes the record keeps in ``level_axes``. Several frames of one acquisition are combined
by :func:`rasterserver.records_analysis.combine` (mean and spread of every parameter).

Definitions, units and signs: ``docs/analysis.md``. Tuned on simulated backs (presets and
``random_back`` seeds 0–99); the benchmark's seeds from 1000 on were never looked at.
"""

from __future__ import annotations

import json
from typing import Any, ClassVar

import numpy as np
from pydantic import Field, SerializerFunctionWrapHandler, model_serializer

from rasterserver.records_analysis import LANDMARKS, SAGITTAL_POINTS, BackShape
from rasterserver.records_surface import Surface
from rasterserver.stage import Stage, StageContext, StageParams

from .back_parameters import PARAMETER_UNITS, back_parameters
from .body_frame import body_frame
from .curvature import surface_curvature
from .landmarks import (
    PIT_RATIO,
    REGION_BELOW,
    ROW_CONCAVITIES,
    TOP_DROP,
    Landmark,
    carried_landmark,
    find_dimples,
    find_vertebra_prominens,
    midpoint,
)
from .level_frame import LevelFrame
from .sacrum_point import find_sacrum_point
from .spinal_midline import MIN_SUPPORT, line_normals, spinal_midline
from .symmetry_line import EDGE_ROOM, edge_room_reason, find_symmetry_line
from .trunk import find_trunk
from .vp_axis import (
    MAX_IMBALANCE,
    MAX_OFFSET,
    check_confidence,
    check_imbalance,
    check_vertebra_prominens,
)

__all__ = ["CARRIED", "NO_VERTICAL", "VP_POSITION", "BackShapeAnalysis", "analyse_back"]

#: The reason of an analysis refused for want of gravity in the calibration.
NO_VERTICAL = (
    "the calibration has no vertical (gravity): clinical heights, inclinations and "
    "horizontal profiles cannot be defined; add the gravity direction to the calibration"
)


#: The reason given for what a VP carried from another visit does not measure.
CARRIED = (
    "VP was carried from another visit through their registration: what measures VP's own "
    "position (trunk length, inclination and imbalance, the sagittal profile, the body frame) "
    "is not measured"
)

#: Parameters that measure VP's own position, not given with a carried VP.
VP_POSITION = (
    "trunk_length",
    "trunk_inclination_mm",
    "trunk_inclination_deg",
    "trunk_imbalance_mm",
    "trunk_imbalance_deg",
    "kyphotic_angle_deg",
    "lordotic_angle_deg",
    "fleche_cervicale_mm",
    "fleche_lombaire_mm",
    "asymmetry_rms_mm",
)


def analyse_back(
    surface: Surface,
    gravity: np.ndarray | None,
    *,
    sigma: float = 5.0,
    vp_axis_offset: float = MAX_OFFSET,
    row_concavities: int = ROW_CONCAVITIES,
    dimple_row_each: bool = True,
    pit_ratio: float | None = PIT_RATIO,
    vp_top_drop: float | None = TOP_DROP,
    vp_max_imbalance: float | None = MAX_IMBALANCE,
    vp_region_below: float = REGION_BELOW,
    vp_min_confidence: float = 0.5,
    midline_support: float = MIN_SUPPORT,
    line_edge_room: float = EDGE_ROOM,
    vp_carried: np.ndarray | None = None,
) -> BackShape:
    """Analyse one smoothed surface.

    Parameters
    ----------
    surface : Surface
        The back as a height field in the world frame.
    gravity : numpy.ndarray or None
        ``(3,)`` direction of gravity (down) in the world frame; None refuses the analysis.
    sigma : float, optional
        Gaussian scale (mm) of the curvature used for the landmarks and the symmetry line.
    vp_axis_offset : float, optional
        Largest distance (mm) of VP from the back's symmetry axis below it
        (:mod:`~rasterserver_plugins.vp_axis`); 0 does not check.
    row_concavities : int, optional
        Other concave candidates at the dimples' height that refuse them (a clothing
        edge, :func:`~rasterserver_plugins.landmarks.find_dimples`); 0 does not check.
    dimple_row_each : bool, optional
        Count them at either dimple's height (version 11), not at the pair's mean height.
    pit_ratio : float or None, optional
        Least ratio of a dimple candidate's weaker to its stronger principal curvature
        (a pit, not a groove); None does not check.
    vp_top_drop : float or None, optional
        VP's candidate at the top of the measured surface is kept when its curvature falls
        below this share of its value above it, inside the surface; None refuses it.
    vp_max_imbalance : float or None, optional
        VP farther than this (mm) beside DM is refused (a shoulder's point, not C7); None
        does not check.
    vp_region_below : float, optional
        How far (in trunk half-widths) VP's search region reaches below the neck line.
    vp_min_confidence : float, optional
        Least confidence of VP kept (:func:`.vp_axis.check_confidence`; version 12); 0
        keeps every VP.
    midline_support : float, optional
        Least share of either side of the rotation's window on measured surface for the
        midline to be measured at a level
        (:data:`~rasterserver_plugins.spinal_midline.MIN_SUPPORT`).
    line_edge_room : float, optional
        Least room (trunk half-widths) between the symmetry line and the measured trunk's
        edge (:data:`~rasterserver_plugins.symmetry_line.EDGE_ROOM`); the line is refused
        closer. 0 does not check.
    vp_carried : numpy.ndarray or None, optional
        ``(3,)`` world position of VP carried from another visit of the patient through their
        registration (:func:`rasterserver.comparison.carry_vp`), used only where this
        surface's own VP is refused; its depth is read from the surface where measured.

    Returns
    -------
    BackShape
        The analysis; empty with a reason when there is no vertical or no trunk.
    """
    if gravity is None:
        return BackShape.empty(NO_VERTICAL)
    try:
        level = LevelFrame.from_gravity(np.asarray(gravity, dtype=float))
    except ValueError as exc:
        return BackShape.empty(f"the calibration's gravity is unusable: {exc}")
    if surface.z.size == 0 or not np.isfinite(surface.z).any():
        detail = f": {surface.reason}" if surface.reason else ""
        return BackShape.empty(f"no surface to analyse{detail}")
    grid = level.level_grid(surface.x0, surface.y0, surface.spacing, surface.z)
    curv = surface_curvature(grid.z, grid.spacing, sigma=sigma)
    trunk = find_trunk(grid.z, grid.spacing)
    if not trunk.found:
        return BackShape.empty(f"no trunk in the surface: {trunk.reason}")
    if trunk.cut:
        return BackShape.empty(
            f"the measured trunk ends at a straight vertical edge on the patient's {trunk.cut}: "
            "the back is not wholly in view (image cropped, or half the back not measured)"
        )

    reasons: dict[str, str] = {}
    vp = find_vertebra_prominens(grid, curv, trunk, top_drop=vp_top_drop, below=vp_region_below)
    # the candidate's height starts the dimples' search even when it is refused below: a
    # shoulder's convex point lies about as high as C7
    dl, dr = find_dimples(
        grid, curv, trunk, vp, row_concavities, pit_ratio=pit_ratio, row_each=dimple_row_each
    )
    if vp_axis_offset > 0:
        vp = check_vertebra_prominens(
            grid, curv, vp, trunk.reference_half_width(), max_offset=vp_axis_offset
        )
    dm = midpoint(grid, curv, dl, dr)
    if vp_max_imbalance is not None:
        vp = check_imbalance(vp, dm, max_imbalance=vp_max_imbalance)
    if vp_min_confidence > 0:
        vp = check_confidence(vp, min_confidence=vp_min_confidence)
    carried = vp_carried is not None and not vp.found
    if carried:
        vp = carried_landmark(grid, curv, level.to_level(np.asarray(vp_carried, dtype=float)))
    sp = find_sacrum_point(grid, curv, trunk, dl, dr)
    found: dict[str, Landmark] = {lm.name: lm for lm in (vp, dl, dr, dm, sp)}
    for lm in found.values():
        if not lm.found:
            reasons[lm.name] = lm.reason

    frame = None
    if carried:
        reasons["frame"] = CARRIED
        reasons["VP"] = "not found on this surface: carried from another visit (vp_carried)"
    elif (
        vp.point is not None
        and dl.point is not None
        and dr.point is not None
        and dm.point is not None
    ):
        frame = body_frame(vp.point, dl.point, dr.point, dm.point)
        if frame is None:
            reasons["frame"] = "VP, DL and DR are degenerate (in line)"
    else:
        reasons["frame"] = "needs VP, DL, DR and DM"

    line = midline = None
    top, bottom = vp.point, dm.point
    if top is not None and bottom is not None:
        line = find_symmetry_line(grid, curv, top, bottom, trunk.reference_half_width())
        refusal = (
            (line.reason or "no symmetry line found")
            if not line.found
            else edge_room_reason(line, grid, trunk, line_edge_room)
        )
        if refusal:
            reasons["symmetry_line"] = refusal
            line = None
    else:
        reasons["symmetry_line"] = "needs VP and DM"
    if line is not None and top is not None and bottom is not None:
        normals = line_normals(grid, line, top, bottom, min_support=midline_support)
        midline = spinal_midline(line, normals, top, bottom)
        refused = int(np.count_nonzero(~np.isfinite(midline.rotation)))
        if refused:
            reasons["midline"] = (
                f"not measured at {refused} of {midline.rotation.size} levels of VP-DM: too "
                "little surface on one side of the symmetry line there"
            )
    else:
        reasons["midline"] = "needs the symmetry line"

    values, sagittal, why = back_parameters(
        grid,
        trunk,
        {k: found[k].point for k in ("VP", "DL", "DR", "DM")},
        line,
        midline,
        None if frame is None else frame[1][0],
    )
    reasons.update(why)
    if carried:  # what measures VP's own position is not measured by a carried VP
        for name in VP_POSITION:
            values.pop(name, None)
            reasons[name] = CARRIED
        sagittal = {}
    parameters = {
        name: {"value": float(values[name]), "unit": unit, "spread": None}
        for name, unit in PARAMETER_UNITS.items()
        if name in values and np.isfinite(values[name])
    }

    def world(points: np.ndarray) -> np.ndarray:
        return level.to_world(points) if points.size else np.zeros((0, 3))

    landmarks = np.full((len(LANDMARKS), 3), np.nan)
    confidence = np.zeros(len(LANDMARKS))
    for k, name in enumerate(LANDMARKS):
        lm = found[name]
        if lm.point is not None:
            landmarks[k] = world(lm.point)
            confidence[k] = lm.confidence
    sagittal_points = np.full((len(SAGITTAL_POINTS), 3), np.nan)
    for k, name in enumerate(SAGITTAL_POINTS):
        if name in sagittal:
            sagittal_points[k] = world(sagittal[name])
    origin, axes = np.full(3, np.nan), np.full((3, 3), np.nan)
    if frame is not None:
        origin, axes = world(frame[0]), level.vectors_to_world(frame[1])
    empty3 = np.zeros((0, 3))
    reason = ""
    if not any(lm.found for lm in (vp, dl, dr)):
        reason = (
            "no back recognised: neither the vertebra prominens nor the lumbar dimples were "
            f"found ({reasons['VP']}; {reasons['DL']})"
        )
    return BackShape(
        x0=grid.x0,
        y0=grid.y0,
        spacing=grid.spacing,
        mean_curvature=curv.mean.astype(np.float32),
        gaussian_curvature=curv.gaussian.astype(np.float32),
        landmarks=landmarks,
        landmark_confidence=confidence,
        frame_origin=origin,
        frame_axes=axes,
        symmetry_line=empty3 if line is None else world(line.points()),
        surface_rotation=np.zeros(0) if midline is None else midline.rotation,
        midline=empty3 if midline is None else world(midline.points),
        parameters=json.dumps(parameters),
        reasons=json.dumps(reasons, sort_keys=True),
        reason=reason,
        max_curvature=curv.k1.astype(np.float32),
        min_curvature=curv.k2.astype(np.float32),
        principal_direction=curv.direction.astype(np.float32),
        sagittal_points=sagittal_points,
        level_axes=level.rotation.copy(),
    )


class BackShapeAnalysis(Stage[Surface, BackShape]):
    """Curvature, landmarks, symmetry line, midline and clinical parameters of a back."""

    name: ClassVar[str] = "analysis.back-shape"
    stage: ClassVar[str] = "analysis"
    # 2: the scoliosis angle reads only tangents with a centred window (not the line's ends)
    # 3: the signed maxima of lateral deviation and surface rotation are refused when the two
    #    sides' extremes are too close for the sign to be decided (back_parameters.SIGN_MARGIN)
    # 4: VP is refused when it lies beside the back's symmetry axis just below it (a
    #    shoulder's convex point where hair hides the nape or an arm joins the shoulder)
    # 5: the lumbar dimples are refused when they lie in a row of concavities across the
    #    lower back (the edge of clothing)
    # 6: the lumbar dimples' candidates must be pits, concave along the body as well as
    #    across it: the grooves of clothing edges and folds are no candidates
    # 7: VP's candidate at the top of the measured surface (hair or a shadow ending it just
    #    above C7) is kept when its curvature is seen to fall above it
    # 8: VP is refused when it lies farther beside DM than a trunk imbalance does (a scapula's
    #    convex point that the axis check of version 4 kept)
    # 9: VP's search region ends 0.45 trunk half-widths below the neck line, not 0.7 (a
    #    convex point of the upper back below a shadowed nape is no candidate); DM is refused
    #    where the skin between the dimples is not measured (version 8 failed there)
    # 10: the spinal midline is refused (not bridged) at levels where either side of the
    #    rotation's window lacks surface, and its parameters when it is refused over more
    #    than a fifth of VP-DM (spinal_midline.MIN_SUPPORT, back_parameters.MIDLINE_MIN_MEASURED);
    #    the dimples' clothing-edge check counts grooves too; the symmetry line is refused
    #    where it runs along the measured trunk's edge (symmetry_line.EDGE_ROOM)
    # 11: the dimples' clothing-edge check counts the row at either dimple's height
    # 12: VP is refused below confidence 0.5 (a weak convex point on the upper back)
    version: ClassVar[str] = "12"
    input_type = Surface
    output_type = BackShape
    requires: ClassVar[tuple[str, ...]] = ("calibration",)

    class Params(StageParams):
        """Parameters of :class:`BackShapeAnalysis`."""

        sigma: float = Field(
            5.0,
            ge=2.0,
            le=30.0,
            description="Gaussian scale (mm) of the curvature for landmarks and symmetry line.",
        )
        vp_axis_offset: float = Field(
            MAX_OFFSET,
            ge=0.0,
            description="Largest distance (mm) of VP from the back's symmetry axis just below "
            "it; a convex point farther off is a shoulder's and is refused. 0 does not check "
            "(version 3).",
        )
        row_concavities: int = Field(
            ROW_CONCAVITIES,
            ge=0,
            description="Refuse the lumbar dimples when this many other concave candidates lie "
            "at their height (a row of concavities across the lower back: the edge of "
            "clothing). 0 does not check (version 4).",
        )
        dimple_row_each: bool = Field(
            True,
            description="Count the row of concavities (row_concavities) at either dimple's "
            "height, not at the pair's mean height (false: version 10).",
        )
        dimple_pit_ratio: float | None = Field(
            PIT_RATIO,
            ge=0.0,
            le=1.0,
            description="Least ratio of a lumbar dimple candidate's weaker to its stronger "
            "principal curvature: a dimple is a pit, a clothing edge or a fold a groove "
            "(ratio near 0). null does not check (version 5).",
        )
        vp_top_drop: float | None = Field(
            TOP_DROP,
            gt=0.0,
            lt=1.0,
            description="VP's candidate at the top of the measured surface (hair or a shadow "
            "ending it just above C7) is kept when its mean curvature falls, up its column "
            "inside the measured surface, below this share of its value: the maximum is seen "
            "on both sides. null refuses every such candidate (version 6).",
        )
        vp_max_imbalance: float | None = Field(
            MAX_IMBALANCE,
            gt=0.0,
            description="Largest lateral distance (mm) of VP from DM (the trunk imbalance); "
            "a convex point farther off is a shoulder's or scapula's and is refused. Raise it "
            "for a patient this far out of balance. null does not check (version 7).",
        )
        vp_region_below: float = Field(
            REGION_BELOW,
            gt=0.0,
            le=1.5,
            description="How far VP's search region reaches below the neck line (where the "
            "neck widens into the shoulders), in trunk half-widths. 0.7 is version 8.",
        )
        vp_min_confidence: float = Field(
            0.5,
            ge=0.0,
            le=1.0,
            description="Refuse VP when its confidence (strength times distinctness) is "
            "below this (a weak convex point on the upper back). 0 does not check "
            "(version 11).",
        )
        midline_support: float = Field(
            MIN_SUPPORT,
            ge=0.0,
            le=1.0,
            description="Least share of either side of the surface rotation's window that "
            "must lie on measured surface for the spinal midline to be measured at a level "
            "(refused there otherwise). 0 measures wherever the fit is possible.",
        )
        line_edge_room: float = Field(
            EDGE_ROOM,
            ge=0.0,
            le=0.5,
            description="Least room, in trunk half-widths, between the symmetry line and the "
            "measured trunk's edge on either side; the line (and what is measured along it) "
            "is refused closer. 0 does not check.",
        )
        vp_carried: tuple[float, float, float] | None = Field(
            None,
            description="World position (mm) of VP carried from another visit of the patient "
            "through their registration (the comparison of visits sets it); used only when "
            "this acquisition's own VP is refused, and then only for the symmetry line and "
            "what is measured along it. null: none.",
        )

        @model_serializer(mode="wrap")
        def _without_unset_carry(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
            # Without a carried VP the parameters serialise (and hash) as before the field
            # existed: the archive's stored analyses stay current.
            data = handler(self)
            if data.get("vp_carried") is None:
                data.pop("vp_carried", None)
            return data

    def run(self, data: Surface, params: Params, context: StageContext) -> BackShape:
        """Analyse ``data`` with the vertical of ``context.calibration``."""
        gravity = getattr(context.calibration, "gravity", None)
        return analyse_back(
            data,
            gravity,
            sigma=params.sigma,
            vp_axis_offset=params.vp_axis_offset,
            row_concavities=params.row_concavities,
            dimple_row_each=params.dimple_row_each,
            pit_ratio=params.dimple_pit_ratio,
            vp_top_drop=params.vp_top_drop,
            vp_max_imbalance=params.vp_max_imbalance,
            vp_region_below=params.vp_region_below,
            vp_min_confidence=params.vp_min_confidence,
            midline_support=params.midline_support,
            line_edge_room=params.line_edge_room,
            vp_carried=None if params.vp_carried is None else np.asarray(params.vp_carried),
        )
