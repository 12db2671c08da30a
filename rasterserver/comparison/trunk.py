"""The body-fixed landmark frame of a visit and its trunk: the part of the back between DM and
VP inside the measured outline, eroded by the edge margin, without the arms."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rasterserver.comparison.thresholds import AXIS_WINDOW, EDGE_MARGIN, ComparisonRefusedError
from rasterserver.comparison.visits import BodyFrame, Visit
from rasterserver.records_analysis import FRAME_LANDMARKS, BackShape
from rasterserver.records_surface import MeshRecord, Surface

#: Below the measured trunk's top (or its neck) the compared trunk of two visits without VP
#: ends this much lower (mm): the hairline's and the neck's rim are the least certain parts.
TOP_MARGIN = 40.0
#: Where the measured trunk narrows to this share of its median half-width, above
#: :data:`NECK_FROM` mm over DM, the neck begins: the compared trunk stays below it.
NECK_WIDTH = 0.6
#: Least height (mm) above DM at which a narrowing counts as the neck (the waist is lower).
NECK_FROM = 150.0
#: Least height (mm) of the trunk compared without either visit's VP.
MIN_HEIGHT = 250.0
#: Gap (mm) along the vertical through DM that ends the measured trunk.
_TOP_GAP = 15.0
#: Erosion (mm) of the outline before its top and widths are read (the rim's single cells).
_TOP_EROSION = 6.0


def landmark_frame(shape: BackShape | BodyFrame, label: str) -> tuple[np.ndarray, np.ndarray]:
    """Origin and axes of a visit's body frame; refused when its landmarks are missing."""
    origin, axes = shape.frame_origin, shape.frame_axes
    if shape.reason or not (np.all(np.isfinite(origin)) and np.all(np.isfinite(axes))):
        missing = [n for n in FRAME_LANDMARKS if shape.landmark(n) is None]
        why = shape.reason or (
            f"landmark {', '.join(missing)} not found" if missing else "degenerate landmarks"
        )
        details = shape.reason_table()
        extra = "; ".join(f"{n}: {details[n]}" for n in missing if n in details)
        raise ComparisonRefusedError(
            f"visit {label or '?'} has no body-fixed frame ({why}{'; ' + extra if extra else ''})"
        )
    return np.asarray(origin, dtype=float), np.asarray(axes, dtype=float)


def landmark_transform(
    a: BackShape | BodyFrame, b: BackShape | BodyFrame, *, labels: tuple[str, str] = ("A", "B")
) -> np.ndarray:
    """The rigid transform putting B's body-fixed frame onto A's.

    A point with body-frame coordinates ``l`` is ``o + Axesᵀ l`` in each world frame, so
    ``p_a = A_axesᵀ B_axes (p_b − o_b) + o_a``.

    Parameters
    ----------
    a, b : BackShape
        The analyses of visits A and B.
    labels : (str, str), optional
        Names of the visits in messages.

    Returns
    -------
    numpy.ndarray
        ``(4, 4)`` homogeneous transform from B's world frame to A's.

    Raises
    ------
    ComparisonRefusedError
        When either visit has no body frame (VP, DL or DR not found), saying which.
    """
    oa, ra = landmark_frame(a, labels[0])
    ob, rb = landmark_frame(b, labels[1])
    rotation = ra.T @ rb
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = oa - rotation @ ob
    return out


@dataclass(frozen=True)
class TrunkFrame:
    """Where a visit's trunk lies: a body frame and the top of the trunk.

    Attributes
    ----------
    origin : numpy.ndarray
        ``(3,)`` DM (world mm).
    axes : numpy.ndarray
        ``(3, 3)`` rows: transverse, vertical, sagittal unit axes.
    top : numpy.ndarray
        ``(3,)`` VP, or where the other visit's trunk height puts it (:func:`pair_frames`).
    """

    origin: np.ndarray
    axes: np.ndarray
    top: np.ndarray

    @property
    def height(self) -> float:
        """The trunk's height above DM along the vertical axis (mm)."""
        return float((self.top - self.origin) @ self.axes[1])


def trunk_frame(visit: Visit) -> TrunkFrame:
    """A visit's body frame (VP, DL, DR) with VP as the trunk's top; refused without it."""
    origin, axes = landmark_frame(visit.shape, visit.label)
    vp = visit.shape.landmark("VP")
    assert vp is not None  # the frame exists, so VP does
    return TrunkFrame(origin, axes, np.asarray(vp, dtype=float))


def _upright(shape: BackShape | BodyFrame) -> tuple[np.ndarray, np.ndarray] | None:
    """Origin DM, transverse DL → DR, vertical the station's up made perpendicular to it."""
    frame = BodyFrame.of(shape)
    dl, dr, dm = (shape.landmark(n) for n in ("DL", "DR", "DM"))
    if shape.reason or dl is None or dr is None or dm is None or frame.gravity is None:
        return None
    up = -np.asarray(frame.gravity, dtype=float)
    if not np.all(np.isfinite(up)) or np.linalg.norm(up) < 1e-6:
        return None
    up /= np.linalg.norm(up)
    across = np.asarray(dr - dl, dtype=float)
    if np.linalg.norm(across) < 1e-6:
        return None
    transverse = across / np.linalg.norm(across)
    vertical = up - (up @ transverse) * transverse
    if np.linalg.norm(vertical) < 0.5:  # the dimples one above the other: no back standing
        return None
    vertical /= np.linalg.norm(vertical)
    return np.asarray(dm, dtype=float), np.stack(
        [transverse, vertical, np.cross(transverse, vertical)]
    )


def pair_frames(
    a: Visit, b: Visit, *, partial: bool = True, neither: bool = True
) -> tuple[TrunkFrame, TrunkFrame, str | None]:
    """The trunk frames of two visits to be compared, and how they were made.

    Both visits' body frames (:func:`trunk_frame`) when both have one. When one visit's VP
    was not found (hair over the nape, two similar convex points) but both have their
    dimples and the other visit its VP, and ``partial``: both frames from DM, DL → DR and
    the station's vertical (the analysis's gravity; one construction for both, so that the
    landmark start does not mix two kinds of frame; the patient stands upright in both, and
    ICP takes up the few degrees of posture), the trunk of the visit without VP as high as
    the other's (one person's trunk, a few months apart). Without gravity in either
    analysis, refused. When neither visit's VP was found (the same hair over the nape at
    both) and ``neither``: the frames alike, the trunk compared up to
    :func:`measured_height` of the lower of the two (below the measured top and the neck,
    less :data:`TOP_MARGIN`), refused under :data:`MIN_HEIGHT`.

    Parameters
    ----------
    a, b : Visit
        The two visits.
    partial : bool, optional
        Allow the frames without one visit's VP.
    neither : bool, optional
        Allow the frames without both visits' VP (with ``partial``).

    Returns
    -------
    TrunkFrame, TrunkFrame
        A's and B's.
    str or None
        None for the body frames; otherwise what was done, for the comparison's record.

    Raises
    ------
    ComparisonRefusedError
        Neither way gives the frames (the reason of the visit without a body frame).
    """
    try:
        return trunk_frame(a), trunk_frame(b), None
    except ComparisonRefusedError as exc:
        if not partial:
            raise
        refusal = exc
    ua, ub = _upright(a.shape), _upright(b.shape)
    va, vb = a.shape.landmark("VP"), b.shape.landmark("VP")
    if ua is None or ub is None or (va is not None and vb is not None):
        raise refusal
    if va is None and vb is None:
        if not neither:
            raise refusal
        return _frames_without_vp(a, b, ua, ub, refusal)
    seen, frame = (va, ua) if va is not None else (vb, ub)
    height = float((np.asarray(seen, dtype=float) - frame[0]) @ frame[1][1])
    if height <= 0.0:
        raise refusal

    def made(visit: Visit, upright: tuple[np.ndarray, np.ndarray]) -> TrunkFrame:
        vp = visit.shape.landmark("VP")
        origin, axes = upright
        top = origin + height * axes[1] if vp is None else np.asarray(vp, dtype=float)
        return TrunkFrame(origin, axes, top)

    lacking, having = (a, b) if va is None else (b, a)
    note = (
        f"VP of visit {lacking.label or '?'} not found: both visits' frames from DM, DL → DR "
        f"and the station's vertical, the trunk {height:.0f} mm high as visit "
        f"{having.label or '?'}'s"
    )
    return made(a, ua), made(b, ub), note


def measured_height(visit: Visit, origin: np.ndarray, up: np.ndarray) -> float:
    """How high above DM the visit's trunk is measured, below its neck (mm).

    Walks up the vertical through DM on the measured outline (eroded by a few millimetres)
    until a gap of more than :data:`_TOP_GAP`; the neck begins, above :data:`NECK_FROM`,
    where the outline's run through the vertical narrows to :data:`NECK_WIDTH` of its
    median half-width over the lower 60 % of the way. On the clinic tuning scenes
    (``benchmarks/clinic_analysis.py``, the 292 bodies with DM) this height less
    :data:`TOP_MARGIN` never reached the true VP: 1.3 mm below it at the closest, 27 mm at
    the median.

    Parameters
    ----------
    visit : Visit
        The visit (its surface's outline).
    origin : numpy.ndarray
        ``(3,)`` DM (world mm).
    up : numpy.ndarray
        ``(3,)`` unit vertical (world).

    Returns
    -------
    float
        The height (mm); 0 when the outline holds no cell of the vertical within
        :data:`_TOP_GAP` of DM.
    """
    from scipy import ndimage

    surface = visit.surface
    if surface.z.size == 0:
        return 0.0
    steps = max(1, round(_TOP_EROSION / surface.spacing))
    valid = ndimage.binary_erosion(surface.valid, iterations=steps, border_value=0)
    ny, nx = valid.shape
    heights: list[float] = []
    half_widths: list[float] = []
    gap = 0.0
    for t in np.arange(0.0, 1000.0, surface.spacing):
        p = origin + t * up
        j = round((p[0] - surface.x0) / surface.spacing)
        i = round((p[1] - surface.y0) / surface.spacing)
        if not (0 <= i < ny and 0 <= j < nx):
            break
        if not valid[i, j]:
            gap += surface.spacing
            if gap > _TOP_GAP:
                break
            continue
        gap = 0.0
        row = valid[i]
        # the run of the row through the vertical: its first and last measured cell
        left = j - int(np.argmin(row[j::-1])) + 1 if not row[: j + 1].all() else 0
        right = j + int(np.argmin(row[j:])) - 1 if not row[j:].all() else nx - 1
        heights.append(float(t))
        half_widths.append(0.5 * (right - left) * surface.spacing)
    if not heights:
        return 0.0
    h, w = np.asarray(heights), np.asarray(half_widths)
    top = float(h[-1])
    lower = w[h < 0.6 * top]
    reference = float(np.median(lower)) if lower.size else float(np.median(w))
    narrow = h[(w < NECK_WIDTH * reference) & (h > NECK_FROM)]
    return min(top, float(narrow.min())) if narrow.size else top


def _frames_without_vp(
    a: Visit,
    b: Visit,
    ua: tuple[np.ndarray, np.ndarray],
    ub: tuple[np.ndarray, np.ndarray],
    refusal: ComparisonRefusedError,
) -> tuple[TrunkFrame, TrunkFrame, str]:
    """Both frames from DM, DL → DR and the vertical; the trunk as high as both measure it."""
    height = (
        min(measured_height(a, ua[0], ua[1][1]), measured_height(b, ub[0], ub[1][1])) - TOP_MARGIN
    )
    if height < MIN_HEIGHT:
        raise ComparisonRefusedError(
            "neither visit's VP was found, and the trunk measured in both reaches only "
            f"{max(height, 0.0):.0f} mm above DM below the neck, less than "
            f"{MIN_HEIGHT:.0f} mm (hair or a shadow over the upper back?); {refusal}"
        )
    frames = tuple(TrunkFrame(o, axes, o + height * axes[1]) for o, axes in (ua, ub))
    note = (
        "VP of neither visit found: both visits' frames from DM, DL → DR and the station's "
        f"vertical, the trunk compared up to {height:.0f} mm above DM (as high as both "
        f"visits measure it below the neck, less {TOP_MARGIN:.0f} mm)"
    )
    return frames[0], frames[1], note


def frame_transform(a: TrunkFrame, b: TrunkFrame) -> np.ndarray:
    """The rigid transform putting frame ``b`` onto frame ``a`` (see
    :func:`landmark_transform`)."""
    rotation = a.axes.T @ b.axes
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = a.origin - rotation @ b.origin
    return out


def _axis_runs(
    eroded: np.ndarray, surface: Surface, dm: np.ndarray, vp: np.ndarray, window: float
) -> np.ndarray:
    """The cells of each grid row's runs of ``eroded`` that come within ``window`` (mm) of the
    DM–VP line at the row's height."""
    from scipy import ndimage

    ny, nx = eroded.shape
    if abs(vp[1] - dm[1]) < surface.spacing:  # no line to follow down the rows
        return eroded
    runs, _count = ndimage.label(eroded, structure=[[0, 0, 0], [1, 1, 1], [0, 0, 0]])
    y = surface.y0 + surface.spacing * np.arange(ny)
    axis = dm[0] + (y - dm[1]) / (vp[1] - dm[1]) * (vp[0] - dm[0])
    x = surface.x0 + surface.spacing * np.arange(nx)
    near = np.abs(x[None, :] - axis[:, None]) <= window
    keep = np.zeros(int(runs.max()) + 1, dtype=bool)
    keep[np.unique(runs[near & eroded])] = True
    keep[0] = False
    return keep[runs]


def trunk_mask(
    visit: Visit,
    points: np.ndarray,
    *,
    margin: float = EDGE_MARGIN,
    window: float | None = AXIS_WINDOW,
    frame: TrunkFrame | None = None,
) -> np.ndarray:
    """Which of ``points`` (world mm) lie on the visit's trunk.

    The trunk is the part of the measured surface between DM and VP along the body frame's
    vertical axis (the head and neck above VP, the buttocks below DM left out), at least
    ``margin`` inside the measured outline (the outline eroded), and in the connected piece
    of it that holds the VP–DM line's midpoint (arms measured apart from the trunk left out).
    In each row of the surface's grid, only the runs of the eroded outline that come within
    ``window`` of the DM–VP line are trunk: an arm beside the trunk, with a gap between
    them in the row, is left out even where it joins the trunk at the shoulder (version 2).

    Parameters
    ----------
    visit : Visit
        The visit (surface and analysis).
    points : numpy.ndarray
        ``(N, 3)`` points in the visit's world frame.
    margin : float, optional
        Erosion of the outline, mm.
    window : float or None, optional
        Half-width (mm) of the band about the DM–VP line a row's run must reach; None: the
        connected piece alone (version 1).
    frame : TrunkFrame, optional
        The frame and top to use (:func:`pair_frames`); the visit's own by default.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool.
    """
    from scipy import ndimage

    points = np.asarray(points, dtype=float).reshape(-1, 3)
    surface = visit.surface
    if surface.z.size == 0 or len(points) == 0:
        return np.zeros(len(points), dtype=bool)
    frame = frame or trunk_frame(visit)
    origin, axes, vp, height = frame.origin, frame.axes, frame.top, frame.height
    local = (points - origin) @ axes.T
    inside = (local[:, 1] >= 0.0) & (local[:, 1] <= height)
    steps = max(1, round(margin / surface.spacing))
    eroded = ndimage.binary_erosion(surface.valid, iterations=steps, border_value=0)
    labels, _count = ndimage.label(eroded)
    ny, nx = surface.shape

    def cells(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        j = np.rint((p[:, 0] - surface.x0) / surface.spacing).astype(np.int64)
        i = np.rint((p[:, 1] - surface.y0) / surface.spacing).astype(np.int64)
        ok = (i >= 0) & (i < ny) & (j >= 0) & (j < nx)
        return np.clip(i, 0, ny - 1), np.clip(j, 0, nx - 1), ok

    mid = 0.5 * (vp + origin)
    mi, mj, mok = cells(mid[None, :])
    piece = labels[mi[0], mj[0]] if mok[0] else 0
    i, j, ok = cells(points)
    on = ok & (labels[i, j] == piece) if piece else ok & eroded[i, j]
    if window is not None:
        on &= _axis_runs(eroded, surface, origin, vp, window)[i, j]
    return inside & on


def submesh(mesh: MeshRecord, keep: np.ndarray) -> MeshRecord:
    """The vertices ``keep`` and the triangles whose three corners are kept, renumbered."""
    index = np.full(len(mesh.vertices), -1, dtype=np.int64)
    index[keep] = np.arange(int(keep.sum()))
    tri = mesh.triangles[np.all(keep[mesh.triangles], axis=1)]
    return MeshRecord(
        vertices=np.array(mesh.vertices[keep]),
        triangles=index[tri].astype(np.int32),
        normals=np.array(mesh.normals[keep]),
    )


def trunk_mesh(
    visit: Visit,
    *,
    margin: float = EDGE_MARGIN,
    window: float | None = AXIS_WINDOW,
    frame: TrunkFrame | None = None,
) -> MeshRecord:
    """The part of the visit's mesh on its trunk (:func:`trunk_mask`)."""
    return submesh(
        visit.mesh,
        trunk_mask(visit, visit.mesh.vertices, margin=margin, window=window, frame=frame),
    )
