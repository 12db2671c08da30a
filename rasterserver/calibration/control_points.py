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


def _rows_from_file(path: Path) -> tuple[list[dict[str, object]], np.ndarray]:
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
    layout = DEFAULT_HOLE_LAYOUT.copy()
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
    if layout.shape != (7, 2):
        raise InputError(
            f"{path.name}: the hole layout must have 7 points (x, y), got {layout.shape}"
        )
    if not np.isfinite(layout).all():
        raise InputError(f"{path.name}: the hole layout holds a coordinate that is not finite")
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
    return ControlPointFile(plates, layout)


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


def _subpixel_centre(
    image: np.ndarray, blob: np.ndarray, bright: np.ndarray, *, level_ring: int = 3
) -> tuple[np.ndarray, float]:
    """First moment of the darkness around one hole; returns ``(u, v)`` and the plate level."""
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
    ring = (d > inner) & (d <= inner + level_ring) & bright[r0:r1, q0:q1]
    if np.count_nonzero(ring) < 8:
        raise InputError("a hole lies too close to the plate's edge to measure its centre")
    level = float(np.median(patch[ring]))
    weight = np.clip(level - patch, 0.0, None) * (d <= inner)
    total = weight.sum()
    return np.array([(weight * xx).sum() / total, (weight * yy).sum() / total]), level


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


def detect_plates(
    image: np.ndarray,
    *,
    layout: np.ndarray | None = None,
    min_plate_area: int = 2000,
    min_hole_area: int = 4,
    name: str = "frame",
) -> list[DetectedPlate]:
    """Find the control planes and their seven identified holes in a projector-off frame.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` uint8/uint16 projector-off frame.
    layout : numpy.ndarray, optional
        ``(7, 2)`` hole layout (plate coordinates); the simulator's by default.
    min_plate_area : int
        Least pixels of a bright component to count as a plate.
    min_hole_area : int
        Least pixels of a dark component inside a plate to count as a hole (noise specks are
        smaller).
    name : str
        Frame name for messages.

    Returns
    -------
    list of DetectedPlate
        Left to right (by the mean hole column).

    Raises
    ------
    InputError
        When a plate shows more or fewer than seven holes, or they do not form the pattern.
    """
    layout = DEFAULT_HOLE_LAYOUT if layout is None else np.asarray(layout, dtype=np.float64)
    if image.ndim != 2:
        raise InputError(f"{name}: a frame must be 2-D, got shape {image.shape}")
    grey = image.astype(np.float32)
    smooth = cv2.GaussianBlur(grey, (5, 5), 1.0)
    scale = 255.0 / max(float(smooth.max()), 1.0)
    threshold, _ = cv2.threshold(
        (smooth * scale).astype(np.uint8), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU
    )
    bright = smooth * scale > threshold
    labels, n = ndimage.label(bright)
    areas = ndimage.sum_labels(np.ones_like(labels), labels, index=np.arange(1, n + 1))
    plates: list[DetectedPlate] = []
    for lab in np.flatnonzero(areas >= min_plate_area) + 1:
        own = labels == lab
        filled = ndimage.binary_fill_holes(own)
        dark = filled & ~own
        hole_labels, n_holes = ndimage.label(dark)
        hole_areas = ndimage.sum_labels(
            np.ones_like(hole_labels), hole_labels, index=np.arange(1, n_holes + 1)
        )
        keep = np.flatnonzero(hole_areas >= min_hole_area) + 1
        rows, cols = np.nonzero(own)
        where = f"{name}: plate at column {cols.mean():.0f}, row {rows.mean():.0f}"
        if keep.size != 7:
            raise InputError(
                f"{where} shows {keep.size} holes, expected 7 "
                "(a hole covered, outside the image or a foreign dark spot?)"
            )
        centres = []
        levels = []
        for h in keep:
            try:
                c, level = _subpixel_centre(grey, hole_labels == h, own)
            except InputError as exc:
                raise InputError(f"{where}: {exc}") from None
            centres.append(c)
            levels.append(level)
        pts = np.array(centres)
        try:
            order, rms = identify_holes(pts, layout)
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
        plates.append(
            DetectedPlate(
                mask=filled,
                holes=pts[order],
                hole_masks=np.isin(hole_labels, keep),
                level=float(np.median(levels)),
                fit_rms=rms,
            )
        )
    plates.sort(key=lambda p: float(p.centre[0]))
    return plates
