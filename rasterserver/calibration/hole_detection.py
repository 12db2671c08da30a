"""The control points measured in a projector-off frame: plates, holes, sub-pixel centres.

A projector-off frame shows the bright aluminium control planes with seven dark holes each
(a 2 x 3 grid and an orientation marker, see ``docs/simulator-scenes.md``). Measurement:

1. plates: Otsu threshold of the lightly blurred frame, connected components larger than
   ``min_plate_area``; each component's filled outline is the plate's mask;
2. holes: the dark components inside a plate's filled mask;
3. sub-pixel centre: first moment of the *darkness* (local plate level minus grey value,
   clipped at 0) over a disc around the hole, the plate level being the median of a ring
   outside it. Weighting by darkness uses the blurred edge pixels symmetrically, so the
   centre is that of the imaged disc. The centroid of an imaged disc is not quite the image
   of its centre (perspective and distortion bend the ellipse): for a 4.5 mm hole on a
   plate facing the camera 2 m away the bias is ~1e-4 px, far below the noise (~0.03 px), so
   it is not corrected; an obliquely viewed plate would need it;
4. identification: the seven points are matched to the seven-point layout by the affine map
   that fits best over all 5040 orderings; the marker breaks every symmetry of the grid, so
   exactly one ordering fits. A plate with a missing, extra or unidentifiable hole is refused.

Which detected plate is which control plate (high or low) is decided later, by the camera
fit (:func:`rasterserver.calibration.camera_calibration.assign_plates`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from rasterserver.calibration.control_points import DEFAULT_HOLE_LAYOUT
from rasterserver.calibration.hole_identification import LayoutMatch, find_patterns, identify_holes
from rasterserver.errors import InputError


@dataclass(frozen=True, eq=False)
class DetectedPlate:
    """A control plane found in a projector-off frame, with its identified holes.

    Attributes
    ----------
    mask : numpy.ndarray
        ``(H, W)`` bool: the plate's filled outline.
    holes : numpy.ndarray
        ``(7, 2)`` sub-pixel hole centres ``(u, v)`` in hole-index order.
    hole_masks : numpy.ndarray
        ``(H, W)`` bool: the dark hole pixels.
    level : float
        Median grey value of the plate (DN).
    fit_rms : float
        Rms of the affine layout fit (px): how well the pattern matched.
    """

    mask: np.ndarray
    holes: np.ndarray
    hole_masks: np.ndarray
    level: float
    fit_rms: float

    @property
    def centre(self) -> np.ndarray:
        """Mean of the hole centres ``(u, v)``."""
        return self.holes.mean(axis=0)

    def interior(self, *, margin: int = 3, hole_margin: int = 4) -> np.ndarray:
        """Plate pixels at least ``margin`` px from its edge and ``hole_margin`` px from holes."""
        kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
        inner = cv2.erode(self.mask.astype(np.uint8), kernel, borderValue=0).astype(bool)
        hk = np.ones((2 * hole_margin + 1, 2 * hole_margin + 1), np.uint8)
        near_hole = cv2.dilate(self.hole_masks.astype(np.uint8), hk).astype(bool)
        return inner & ~near_hole


@dataclass(frozen=True, eq=False)
class _Blobs:
    """Dark, compact, hole-sized spots of a frame (candidates for holes)."""

    labels: np.ndarray  # (H, W) int32: blob k has label k + 1; 0 elsewhere
    centres: np.ndarray  # (n, 2) rough (u, v): centroid of the blob's pixels
    areas: np.ndarray  # (n,) pixels
    usable: np.ndarray  # (n,) bool: not cut by the image border
    dark: np.ndarray  # (H, W) bool: every pixel darker than its surroundings


def _dark_blobs(
    grey: np.ndarray, *, max_hole_px: int, min_hole_area: int, min_contrast: float
) -> _Blobs:
    """Spots darker than their surroundings by ``min_contrast`` (a fraction), hole-sized.

    The surroundings' level is a grey closing with a disc wider than any hole: it follows
    uneven light and a base as bright as the plates, unlike a global threshold. Long dark
    things (the margin of a dark base beside a bright plate, gaps) are not holes: a blob
    must fit the closing's disc and be no more elongated than 3:1.
    """
    smooth = cv2.GaussianBlur(grey, (5, 5), 1.0)
    size = 2 * (max_hole_px // 2) + 3
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    level = cv2.morphologyEx(smooth, cv2.MORPH_CLOSE, disc, borderType=cv2.BORDER_REPLICATE)
    contrast = (level - smooth) / np.maximum(level, 1.0)
    dark = contrast > min_contrast
    labels, n = ndimage.label(dark)
    if n == 0:
        empty = np.zeros((0, 2))
        return _Blobs(np.zeros(grey.shape, np.int32), empty, np.zeros(0), np.zeros(0, bool), dark)
    index = np.arange(1, n + 1)
    ones = np.ones_like(labels)
    area = ndimage.sum_labels(ones, labels, index)
    rows, cols = np.indices(labels.shape)
    mr = ndimage.mean(rows, labels, index)
    mc = ndimage.mean(cols, labels, index)
    vr = ndimage.mean(rows.astype(np.float64) ** 2, labels, index) - mr**2
    vc = ndimage.mean(cols.astype(np.float64) ** 2, labels, index) - mc**2
    vrc = ndimage.mean(rows.astype(np.float64) * cols, labels, index) - mr * mc
    spread = np.sqrt(((vr - vc) / 2) ** 2 + vrc**2)
    major, minor = (vr + vc) / 2 + spread, np.maximum((vr + vc) / 2 - spread, 1e-3)
    boxes = ndimage.find_objects(labels)
    height, width = labels.shape
    extent = np.array([max(b[0].stop - b[0].start, b[1].stop - b[1].start) for b in boxes])
    touches = np.array(
        [
            b[0].start == 0 or b[1].start == 0 or b[0].stop == height or b[1].stop == width
            for b in boxes
        ]
    )
    keep = (area >= min_hole_area) & (extent <= max_hole_px) & (major <= 9.0 * minor)
    relabel = np.zeros(n + 1, np.int32)
    relabel[index[keep]] = np.arange(1, int(keep.sum()) + 1)
    return _Blobs(
        labels=relabel[labels],
        centres=np.column_stack([mc[keep], mr[keep]]),
        areas=area[keep],
        usable=~touches[keep],
        dark=dark,
    )


def _subpixel_centre(
    image: np.ndarray, blob: np.ndarray, dark: np.ndarray, *, level_ring: int = 3
) -> tuple[np.ndarray, float]:
    """First moment of the darkness around one hole; returns ``(u, v)`` and the plate level.

    The plate level is a plane fitted to a ring of pixels just outside the blurred disc (not
    a constant): under uneven light the plate's brightness slopes across the hole, and a
    constant level would pull the centre towards the darker side.
    """
    rows, cols = np.nonzero(blob)
    c0 = np.array([cols.mean(), rows.mean()])
    radius = np.sqrt(rows.size / np.pi)
    reach = int(np.ceil(radius + 3 + level_ring)) + 1
    r0, r1 = max(int(c0[1]) - reach, 0), min(int(c0[1]) + reach + 1, image.shape[0])
    q0, q1 = max(int(c0[0]) - reach, 0), min(int(c0[0]) + reach + 1, image.shape[1])
    patch = image[r0:r1, q0:q1].astype(np.float64)
    yy, xx = np.mgrid[r0:r1, q0:q1]
    d = np.hypot(xx - c0[0], yy - c0[1])
    inner = radius + 2.5  # the disc plus the blur of its edge
    ring = (d > inner) & (d <= inner + level_ring) & ~dark[r0:r1, q0:q1]
    if np.count_nonzero(ring) < 12:
        raise InputError("a hole lies too close to the plate's edge to measure its centre")
    design = np.column_stack([np.ones(np.count_nonzero(ring)), xx[ring] - c0[0], yy[ring] - c0[1]])
    values = patch[ring]
    coef = np.linalg.lstsq(design, values, rcond=None)[0]
    # one trimming pass: a speck or an edge in the ring must not tilt the plane
    resid = values - design @ coef
    mad = max(float(np.median(np.abs(resid))), 0.5)
    good = np.abs(resid) <= 4.0 * 1.4826 * mad
    if np.count_nonzero(good) >= 12:
        coef = np.linalg.lstsq(design[good], values[good], rcond=None)[0]
    level = coef[0] + coef[1] * (xx - c0[0]) + coef[2] * (yy - c0[1])
    weight = np.clip(level - patch, 0.0, None) * (d <= inner)
    total = weight.sum()
    if not total > 0:
        raise InputError("a hole is not darker than the plate around it")
    return np.array([(weight * xx).sum() / total, (weight * yy).sum() / total]), float(coef[0])


def _region(
    points: np.ndarray, layout: np.ndarray, grow: float, shape: tuple[int, int]
) -> np.ndarray:
    """Mask of the layout's convex hull grown by ``grow`` mm, mapped by the affine fit."""
    design = np.column_stack([layout, np.ones(7)])
    affine = np.linalg.lstsq(design, points, rcond=None)[0]
    angles = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    ring = grow * np.column_stack([np.cos(angles), np.sin(angles)])
    grown = (layout[:, None, :] + ring[None]).reshape(-1, 2)
    image = np.column_stack([grown, np.ones(len(grown))]) @ affine
    hull = cv2.convexHull(np.round(image * 16).astype(np.int32))
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def _hull_mask(pixels: np.ndarray) -> np.ndarray:
    """The convex hull of the true pixels of a mask, filled.

    Of the seven holes' dark pixels: every hole lies on the plate and the plate is convex, so
    the hull is plate, whatever surrounds the plate.
    """
    rows, cols = np.nonzero(pixels)
    hull = cv2.convexHull(np.column_stack([cols, rows]).astype(np.int32))
    mask = np.zeros(pixels.shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool)


def detect_plates(
    image: np.ndarray,
    *,
    layout: np.ndarray | None = None,
    expected: int | None = None,
    max_hole_px: int = 31,
    min_hole_area: int = 4,
    min_contrast: float = 0.35,
    tolerance: float = 0.04,
    max_anisotropy: float = 2.5,
    name: str = "frame",
) -> list[DetectedPlate]:
    """Find the control planes by their hole pattern in a projector-off frame.

    Nothing is assumed about the background: the base may be as bright as the plates, the
    plates' sides and columns may show, the light may be uneven. Steps: dark compact spots
    (:func:`_dark_blobs`, darker than a local grey closing) → every affine placement of the
    layout on them (:func:`find_patterns`) → per placement with all seven holes, the order
    by :func:`identify_holes` and sub-pixel centres. Refused rather than guessed: two
    placements sharing a spot (ambiguous), another hole-sized dark spot within the pattern
    (a foreign spot could be taken for a hole), fewer placements than ``expected`` where a
    partial one (5-6 holes) shows a plate with a hole covered.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` uint8/uint16 projector-off frame.
    layout : numpy.ndarray, optional
        ``(7, 2)`` hole layout (plate coordinates); the simulator's by default.
    expected : int, optional
        How many plates the frame should show. When fewer complete patterns are found and a
        partial one is there, the refusal names it (``shows 6 holes, expected 7``).
    max_hole_px : int
        Largest hole diameter in the image (px); wider dark areas are not holes.
    min_hole_area : int
        Least pixels of a dark spot to count as a hole (noise specks are smaller).
    min_contrast : float
        Least darkness of a hole pixel relative to its surroundings (0-1).
    tolerance : float
        Largest distance of a hole from the layout's affine image, as a fraction of the
        pattern's rms radius in the image.
    max_anisotropy : float
        Largest ratio of the affine map's singular values (a plate seen at up to ~65°).
    name : str
        Frame name for messages.

    Returns
    -------
    list of DetectedPlate
        Left to right (by the mean hole column). ``mask`` is the convex hull of the seven
        holes' dark pixels: the part of the plate the pattern proves to be plate.

    Raises
    ------
    InputError
        An ambiguous pattern, a foreign dark spot within a plate's pattern, a plate whose
        pattern lacks holes (with ``expected``), holes too close to an edge to measure.
    """
    layout = DEFAULT_HOLE_LAYOUT if layout is None else np.asarray(layout, dtype=np.float64)
    if image.ndim != 2:
        raise InputError(f"{name}: a frame must be 2-D, got shape {image.shape}")
    grey = image.astype(np.float32)
    blobs = _dark_blobs(
        grey, max_hole_px=max_hole_px, min_hole_area=min_hole_area, min_contrast=min_contrast
    )
    if len(blobs.centres) > 2000:
        raise InputError(
            f"{name}: {len(blobs.centres)} dark spots: not a projector-off frame "
            "of the control-point body (too noisy or the projector on?)"
        )
    matches = find_patterns(
        blobs.centres, layout, tolerance=tolerance, max_anisotropy=max_anisotropy
    )
    complete = [m for m in matches if m.found == 7]

    def where(points: np.ndarray) -> str:
        u, v = points.mean(axis=0)
        return f"{name}: plate at column {u:.0f}, row {v:.0f}"

    # a spot claimed by two complete placements: which seven are the holes is not decided
    for m1, m2 in itertools.combinations(complete, 2):
        if set(m1.blobs) & set(m2.blobs) and set(m1.blobs) != set(m2.blobs):
            raise InputError(
                f"{where(blobs.centres[list(m1.blobs)])}: the hole pattern fits two sets of "
                "dark spots that share holes (ambiguous; a foreign dark spot near a hole?)"
            )
    unique: dict[frozenset[int], LayoutMatch] = {}
    for m in complete:
        unique.setdefault(frozenset(m.blobs), m)
    spacing = np.linalg.norm(layout[:, None] - layout[None], axis=2)
    grow = 0.3 * float(spacing[spacing > 0].min())
    plates: list[DetectedPlate] = []
    for m in unique.values():
        members = list(m.blobs)
        rough = blobs.centres[members]
        if not blobs.usable[members].all():
            raise InputError(f"{where(rough)}: a hole is cut by the image's border")
        # any other hole-sized dark spot within the pattern could be a hole mistaken for
        # another one's neighbour: refuse, as the count of holes says
        region = _region(rough, layout, grow, grey.shape)
        inside = set(np.unique(blobs.labels[region]).tolist()) - {0}
        extra = inside - {b + 1 for b in members}
        if extra:
            raise InputError(
                f"{where(rough)} shows {7 + len(extra)} holes, expected 7 "
                "(a foreign dark spot on the plate?)"
            )
        centres, levels = [], []
        for b in members:
            try:
                c, level = _subpixel_centre(grey, blobs.labels == b + 1, blobs.dark)
            except InputError as exc:
                raise InputError(f"{where(rough)}: {exc}") from None
            centres.append(c)
            levels.append(level)
        pts = np.array(centres)
        try:
            order, rms = identify_holes(pts, layout)
        except InputError as exc:
            raise InputError(f"{where(rough)}: {exc}") from None
        hole_masks = np.isin(blobs.labels, [b + 1 for b in members])
        plates.append(
            DetectedPlate(
                mask=_hull_mask(hole_masks),
                holes=pts[order],
                hole_masks=hole_masks,
                level=float(np.median(levels)),
                fit_rms=rms,
            )
        )
    if expected is not None and len(plates) < expected:
        used = set().union(*(set(m.blobs) for m in complete)) if complete else set()
        partial = [m for m in matches if m.found < 7 and not set(m.blobs) & used]
        if partial:
            best = max(partial, key=lambda m: (m.found, -m.rms))
            rough = blobs.centres[[b for b in best.blobs if b >= 0]]
            raise InputError(
                f"{where(rough)} shows {best.found} holes, expected 7 "
                "(a hole covered, outside the image or not dark?)"
            )
    plates.sort(key=lambda p: float(p.centre[0]))
    return plates
