"""Control points: the 3-D coordinates of the holes, and their measurement in the frames.

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

import csv
import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from rasterserver.errors import InputError

__all__ = [
    "DEFAULT_HOLE_LAYOUT",
    "ControlPointFile",
    "DetectedPlate",
    "PlatePoints",
    "detect_plates",
    "identify_holes",
    "load_control_points",
]

#: The simulator's hole layout (plate coordinates, mm): 2 x 3 grid row by row, then marker.
DEFAULT_HOLE_LAYOUT = np.array(
    [
        [-40.0, -120.0],
        [40.0, -120.0],
        [-40.0, 0.0],
        [40.0, 0.0],
        [-40.0, 120.0],
        [40.0, 120.0],
        [20.0, 60.0],
    ]
)

_PERMUTATIONS = np.array(list(itertools.permutations(range(7))), dtype=np.int64)


@dataclass(frozen=True)
class PlatePoints:
    """The seven control points of one control plane in one configuration.

    Attributes
    ----------
    configuration : int
        Configuration number (0, 1, 2 for the seed's body).
    plate : str
        Plate label (``"high"``, ``"low"``).
    ids : tuple of str
        Point identifiers, in hole-index order.
    xyz : numpy.ndarray
        ``(7, 3)`` world coordinates (mm), in hole-index order.
    """

    configuration: int
    plate: str
    ids: tuple[str, ...]
    xyz: np.ndarray

    def plane(self) -> tuple[np.ndarray, float]:
        """Best-fit plane ``n @ p = d`` through the points; ``n`` points away from the camera."""
        centre = self.xyz.mean(axis=0)
        _, _, vt = np.linalg.svd(self.xyz - centre)
        n = vt[2] if vt[2, 2] >= 0 else -vt[2]
        return n, float(n @ centre)


@dataclass(frozen=True)
class ControlPointFile:
    """A control-point file: every plate's points, grouped by configuration.

    Attributes
    ----------
    plates : dict
        ``{configuration: [PlatePoints, ...]}``.
    layout : numpy.ndarray
        ``(7, 2)`` hole layout in plate coordinates (mm).
    """

    plates: dict[int, list[PlatePoints]]
    layout: np.ndarray = field(default_factory=lambda: DEFAULT_HOLE_LAYOUT.copy())

    @property
    def configurations(self) -> list[int]:
        """The configuration numbers, ascending."""
        return sorted(self.plates)


def _rows_from_file(path: Path) -> tuple[list[dict[str, object]], np.ndarray | None]:
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a control-point file")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such control-point file") from None
    except UnicodeDecodeError:
        raise InputError(f"{path.name}: not a control-point file (not UTF-8 text)") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the control-point file ({exc.strerror})") from None
    layout: np.ndarray | None = None
    if path.suffix.lower() == ".json":
        try:
            document = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"{path.name}: not JSON ({exc})") from None
        except RecursionError:
            raise InputError(f"{path.name}: not a control-point file: nested too deeply") from None
        if not isinstance(document, dict) or not isinstance(document.get("points"), list):
            raise InputError(f"{path.name}: not a control-point document (no 'points' list)")
        hole_layout = document.get("hole_layout", {})
        if not isinstance(hole_layout, dict):
            raise InputError(f"{path.name}: 'hole_layout' must be an object")
        given = hole_layout.get("plate_coordinates_mm")
        if given is not None:
            try:
                layout = np.asarray(given, dtype=np.float64)
            except (TypeError, ValueError):
                raise InputError(
                    f"{path.name}: the hole layout must be 7 points (x, y) in mm"
                ) from None
        return document["points"], layout
    return list(csv.DictReader(text.splitlines())), layout


def load_control_points(path: str | Path) -> ControlPointFile:
    """Read control points (``rasterserver.control_points/1`` JSON, or the same fields as CSV).

    Parameters
    ----------
    path : str or Path
        The file written by ``rasterserver simulate calibration-body`` or a clinic's survey.

    Returns
    -------
    ControlPointFile

    Raises
    ------
    InputError
        Unreadable file, missing fields, a coordinate that is not a finite number (NaN or
        infinity would make the camera fit fail), or a plate without exactly one point per
        hole index.
    """
    path = Path(path)
    rows, layout = _rows_from_file(path)
    if layout is not None:
        if layout.shape != (7, 2):
            raise InputError(
                f"{path.name}: the hole layout must have 7 points (x, y), got {layout.shape}"
            )
        if not np.isfinite(layout).all():
            raise InputError(
                f"{path.name}: the hole layout holds a coordinate that is not finite"
            )
    groups: dict[tuple[int, str], dict[int, tuple[str, np.ndarray]]] = {}
    for i, row in enumerate(rows):
        try:
            key = (int(row["configuration"]), str(row["plate"]))  # type: ignore[call-overload]
            index = int(row["index"])  # type: ignore[call-overload]
            xyz = np.array([float(row[c]) for c in "xyz"])  # type: ignore[arg-type]
            ident = str(row.get("id", f"c{key[0]}-{key[1]}-{index}"))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{path.name}: point {i} lacks a usable field ({exc})") from None
        if not np.isfinite(xyz).all():
            raise InputError(
                f"{path.name}: point {ident} has a coordinate that is not a finite number "
                f"(x, y, z = {', '.join(str(v) for v in xyz)})"
            )
        if not 0 <= index < 7:
            raise InputError(f"{path.name}: point {ident} has hole index {index}, not 0-6")
        slot = groups.setdefault(key, {})
        if index in slot:
            raise InputError(
                f"{path.name}: two points for hole {index} of {key[1]} plate, "
                f"configuration {key[0]}"
            )
        slot[index] = (ident, xyz)
    plates: dict[int, list[PlatePoints]] = {}
    for (k, plate), slot in sorted(groups.items()):
        if len(slot) != 7:
            missing = sorted(set(range(7)) - set(slot))
            raise InputError(
                f"{path.name}: {plate} plate of configuration {k} lacks holes {missing}"
            )
        ids = tuple(slot[j][0] for j in range(7))
        xyz = np.stack([slot[j][1] for j in range(7)])
        plates.setdefault(k, []).append(PlatePoints(k, plate, ids, xyz))
    if not plates:
        raise InputError(f"{path.name}: no control points")
    if layout is None:
        # a CSV (or JSON without a layout) carries the layout in its points: the first
        # plate's, in its own plane; every plate is checked against it below
        layout = plate_coordinates(next(iter(plates.values()))[0].xyz)
    check_layout(layout, name=path.name)
    for group in plates.values():
        for pp in group:
            _check_plate_layout(pp, layout, name=path.name)
    return ControlPointFile(plates, layout)


def plate_coordinates(xyz: np.ndarray) -> np.ndarray:
    """Seven points ``(7, 3)`` of one plate in its plane's coordinates ``(7, 2)`` (mm).

    Axes: ``x`` along the world X projected into the plane, ``y = n x x`` with the plane's
    normal ``n`` pointing away from the camera (+Z), so ``y`` runs downwards like the
    world's Y and the plate coordinates have the handedness the camera sees.
    """
    centre = xyz.mean(axis=0)
    _, _, vt = np.linalg.svd(xyz - centre)
    n = vt[2] if vt[2, 2] >= 0 else -vt[2]
    e1 = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(e1) < 0.1:  # a plate facing sideways: start from the world's Y
        e1 = np.array([0.0, 1.0, 0.0]) - n[1] * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    rel = xyz - centre
    return np.column_stack([rel @ e1, rel @ e2])


def _similarity_rms(src: np.ndarray, dst: np.ndarray, *, mirror: bool = False) -> float:
    """Rms residual (dst units) of the best proper 2-D similarity (or mirrored) src → dst."""
    a = src - src.mean(axis=0)
    b = dst - dst.mean(axis=0)
    if mirror:
        a = a * [-1.0, 1.0]
    za, zb = a[:, 0] + 1j * a[:, 1], b[:, 0] + 1j * b[:, 1]
    s = np.vdot(za, zb) / max(np.vdot(za, za).real, 1e-12)
    return float(np.sqrt(np.mean(np.abs(s * za - zb) ** 2)))


def check_layout(layout: np.ndarray, *, name: str = "control points") -> None:
    """Refuse a hole layout that cannot identify its points in an image.

    Raises
    ------
    InputError
        Holes nearly on one line or coinciding, or a symmetric layout (an affine map other
        than the identity takes the holes onto each other: which is which would be a guess).
    """
    centred = layout - layout.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    gaps = np.linalg.norm(layout[:, None] - layout[None], axis=2)[np.triu_indices(7, 1)]
    if sv[1] < 0.05 * sv[0] or gaps.min() < 0.02 * sv[0]:
        raise InputError(f"{name}: the hole layout's points lie nearly on one line or coincide")
    other = layout_self_map(layout)
    if other is not None:
        moved = [f"{j}->{int(other[j])}" for j in range(7) if other[j] != j]
        raise InputError(
            f"{name}: the hole layout is symmetric (an affine map takes it onto itself, holes "
            f"{', '.join(moved)}): its points cannot be told apart in an image"
        )


def _check_plate_layout(pp: PlatePoints, layout: np.ndarray, *, name: str) -> None:
    """The plate's surveyed points must be the layout moved rigidly (within 0.5 mm rms)."""
    local = plate_coordinates(pp.xyz)
    radius = float(np.sqrt(((layout - layout.mean(axis=0)) ** 2).sum(axis=1).mean()))
    tol = max(0.5, 0.01 * radius)
    rms = _similarity_rms(layout, local)
    if rms <= tol:
        return
    what = f"{name}: the {pp.plate} plate of configuration {pp.configuration}"
    if _similarity_rms(layout, local, mirror=True) <= tol:
        raise InputError(f"{what} is the mirror image of the hole layout (x or y reversed?)")
    raise InputError(
        f"{what} does not have the hole layout ({rms:.1f} mm rms off it): points mislabelled "
        "or another layout"
    )


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
        [b[0].start == 0 or b[1].start == 0 or b[0].stop == height or b[1].stop == width
         for b in boxes]
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


def identify_holes(
    points: np.ndarray, layout: np.ndarray, *, tolerance: float = 0.03
) -> tuple[np.ndarray, float]:
    """Order seven image points as the layout's holes by the best affine fit.

    Parameters
    ----------
    points : numpy.ndarray
        ``(7, 2)`` image points in any order.
    layout : numpy.ndarray
        ``(7, 2)`` hole layout in plate coordinates.
    tolerance : float
        Largest accepted rms misfit as a fraction of the pattern's rms radius in the image (a
        plate seen obliquely departs from an affine image by a few per mille).

    Returns
    -------
    order : numpy.ndarray
        ``(7,)``: ``points[order[j]]`` is hole ``j``.
    rms : float
        Rms misfit (px).

    Raises
    ------
    InputError
        When no ordering fits, or two fit equally well.
    """
    design = np.column_stack([layout, np.ones(7)])
    pinv = np.linalg.pinv(design)
    candidates = points[_PERMUTATIONS]  # (5040, 7, 2)
    maps = np.einsum("ij,pjk->pik", pinv, candidates)  # (5040, 3, 2)
    misfit = np.einsum("ij,pjk->pik", design, maps) - candidates
    rms = np.sqrt((misfit**2).sum(axis=2).mean(axis=1))
    linear = maps[:, :2, :]
    det = linear[:, 0, 0] * linear[:, 1, 1] - linear[:, 0, 1] * linear[:, 1, 0]
    # the camera sees the plate's front: a mirrored match is not a view of the plate
    rms = np.where(det > 0, rms, np.inf)
    best = int(np.argmin(rms))
    # the pattern's size in the image: its rms radius times the map's scale
    radius = np.sqrt(((layout - layout.mean(axis=0)) ** 2).sum(axis=1).mean())
    spacing = max(float(np.sqrt(abs(det[best])) * radius), 1e-9)
    ranked = np.sort(rms)
    if not ranked[0] <= tolerance * spacing:
        raise InputError(
            f"the holes do not form the control-point pattern (best fit off by "
            f"{ranked[0]:.1f} px rms): a hole mis-detected, or a foreign dark spot"
        )
    if ranked[1] <= 2.0 * tolerance * spacing:
        raise InputError("the hole pattern is ambiguous: two orderings of the holes fit")
    return _PERMUTATIONS[best], float(ranked[0])




def layout_self_map(layout: np.ndarray, *, tolerance: float = 0.06) -> np.ndarray | None:
    """An ordering of the layout other than the identity that an affine map fits, if any.

    A layout with such a self-map (a symmetric pattern: a regular grid, a circle of holes)
    cannot identify its points in an image; :func:`load_control_points` refuses it. Mirror
    images count too unless the plates are seen from the front only: they are, so only maps
    with a positive determinant are tried (as :func:`identify_holes` does).

    Returns
    -------
    numpy.ndarray or None
        ``(7,)`` the other ordering, or ``None`` when only the identity fits.
    """
    layout = np.asarray(layout, dtype=np.float64)
    design = np.column_stack([layout, np.ones(7)])
    pinv = np.linalg.pinv(design)
    candidates = layout[_PERMUTATIONS]
    maps = np.einsum("ij,pjk->pik", pinv, candidates)
    misfit = np.einsum("ij,pjk->pik", design, maps) - candidates
    rms = np.sqrt((misfit**2).sum(axis=2).mean(axis=1))
    linear = maps[:, :2, :]
    det = linear[:, 0, 0] * linear[:, 1, 1] - linear[:, 0, 1] * linear[:, 1, 0]
    radius = np.sqrt(((layout - layout.mean(axis=0)) ** 2).sum(axis=1).mean())
    # the image's scale is sqrt|det| times the layout's: compare misfits in the image's terms
    scaled = rms / np.maximum(np.sqrt(np.abs(det)), 1e-9)
    fits = (det > 0.05) & (scaled <= tolerance * radius)
    fits[0] = False  # permutation 0 is the identity
    hits = np.flatnonzero(fits)
    return None if hits.size == 0 else _PERMUTATIONS[hits[np.argmin(scaled[hits])]]


def _bases(layout: np.ndarray) -> list[tuple[int, int, int]]:
    """Two disjoint, well-conditioned layout triples: any one missing hole spares one."""
    triples = list(itertools.combinations(range(7), 3))

    def area(t: tuple[int, int, int]) -> float:
        a, b, c = layout[list(t)]
        (x1, y1), (x2, y2) = b - a, c - a
        return abs(float(x1 * y2 - x2 * y1))

    first = max(triples, key=area)
    second = max((t for t in triples if not set(t) & set(first)), key=area)
    return [first, second]


@dataclass(frozen=True)
class _Match:
    """Blobs that an affine image of the layout puts at its holes (-1: no blob there)."""

    blobs: tuple[int, ...]
    rms: float

    @property
    def found(self) -> int:
        return sum(b >= 0 for b in self.blobs)


def _find_patterns(
    centres: np.ndarray, layout: np.ndarray, *, tolerance: float, max_anisotropy: float
) -> list[_Match]:
    """Every placement of the layout on the blobs with at least five holes in place.

    Hypotheses: an ordered pair of blobs as two points of a layout triple gives a similarity;
    the blobs near the similarity's third point (loosely, for oblique views) complete an
    affine map; the map predicts all seven holes, each taken by the nearest blob within
    ``tolerance`` times the pattern's rms radius in the image. Vectorised over hypotheses.
    """
    n = len(centres)
    if n < 3:
        return []
    tree = cKDTree(centres)
    radius_mm = float(np.sqrt(((layout - layout.mean(axis=0)) ** 2).sum(axis=1).mean()))
    zc = centres[:, 0] + 1j * centres[:, 1]
    zl = layout[:, 0] + 1j * layout[:, 1]
    i, j = np.nonzero(~np.eye(n, dtype=bool))
    found: dict[tuple[int, ...], _Match] = {}
    for a, b, c in _bases(layout):
        scale = (zc[j] - zc[i]) / (zl[b] - zl[a])
        guess = zc[i] + scale * (zl[c] - zl[a])
        loose = 0.5 * np.abs(scale) * abs(zl[c] - zl[a])
        near = tree.query_ball_point(np.column_stack([guess.real, guess.imag]), r=loose)
        lengths = np.fromiter((len(x) for x in near), np.int64, len(near))
        if lengths.sum() == 0:
            continue
        ii, jj = np.repeat(i, lengths), np.repeat(j, lengths)
        kk = np.concatenate([np.asarray(x, np.int64) for x in near if x])
        ok = (kk != ii) & (kk != jj)
        ii, jj, kk = ii[ok], jj[ok], kk[ok]
        if ii.size == 0:
            continue
        src = np.array([[*layout[a], 1.0], [*layout[b], 1.0], [*layout[c], 1.0]])
        inv = np.linalg.inv(src)  # affine A (3 x 2): src @ A = the three image points
        dst = np.stack([centres[ii], centres[jj], centres[kk]], axis=1)  # (T, 3, 2)
        maps = np.einsum("ij,tjk->tik", inv, dst)
        lin = maps[:, :2, :]
        det = lin[:, 0, 0] * lin[:, 1, 1] - lin[:, 0, 1] * lin[:, 1, 0]
        sv = np.linalg.svd(lin, compute_uv=False)
        keep = (det > 0) & (sv[:, 1] > 0) & (sv[:, 0] <= max_anisotropy * sv[:, 1])
        maps, sv = maps[keep], sv[keep]
        if maps.shape[0] == 0:
            continue
        predicted = np.einsum("ij,tjk->tik", np.column_stack([layout, np.ones(7)]), maps)
        dist, idx = tree.query(predicted.reshape(-1, 2))
        dist, idx = dist.reshape(-1, 7), idx.reshape(-1, 7)
        tol = np.maximum(tolerance * np.sqrt(sv[:, 0] * sv[:, 1]) * radius_mm, 1.5)
        hit = dist <= tol[:, None]
        enough = hit.sum(axis=1) >= 5
        for row in np.flatnonzero(enough):
            blobs = tuple(int(x) if h else -1 for x, h in zip(idx[row], hit[row], strict=True))
            taken = [x for x in blobs if x >= 0]
            if len(set(taken)) != len(taken):
                continue  # two holes on one blob: not a placement
            if blobs not in found:
                found[blobs] = _Match(blobs, float(np.sqrt(np.mean(dist[row][hit[row]] ** 2))))
    return list(found.values())


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
    layout on them (:func:`_find_patterns`) → per placement with all seven holes, the order
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
    blobs = _dark_blobs(grey, max_hole_px=max_hole_px, min_hole_area=min_hole_area,
                        min_contrast=min_contrast)
    if len(blobs.centres) > 2000:
        raise InputError(f"{name}: {len(blobs.centres)} dark spots: not a projector-off frame "
                         "of the control-point body (too noisy or the projector on?)")
    matches = _find_patterns(blobs.centres, layout, tolerance=tolerance,
                             max_anisotropy=max_anisotropy)
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
    unique: dict[frozenset[int], _Match] = {}
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
