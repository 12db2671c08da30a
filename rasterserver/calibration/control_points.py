"""Control points: the 3-D coordinates of the holes, as the control-point file gives them.

The file (JSON ``rasterserver.control_points/1`` or CSV) is read and checked here; the holes are
measured in the frames by :mod:`rasterserver.calibration.hole_detection` and matched to the
layout by :mod:`rasterserver.calibration.hole_identification`."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rasterserver.calibration.hole_identification import layout_self_map
from rasterserver.errors import InputError

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
    if layout is None:
        # a CSV (or JSON without a layout) carries the layout in its points: the first
        # plate's, in its own plane; every plate is checked against it below
        layout = plate_coordinates(next(iter(plates.values()))[0].xyz)
    check_layout(layout, name=path.name)
    for group in plates.values():
        for pp in group:
            check_plate_layout(pp, layout, name=path.name)
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


def similarity_rms(src: np.ndarray, dst: np.ndarray, *, mirror: bool = False) -> float:
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


def check_plate_layout(pp: PlatePoints, layout: np.ndarray, *, name: str) -> None:
    """The plate's surveyed points must be the layout moved rigidly (within 0.5 mm rms)."""
    local = plate_coordinates(pp.xyz)
    radius = float(np.sqrt(((layout - layout.mean(axis=0)) ** 2).sum(axis=1).mean()))
    tol = max(0.5, 0.01 * radius)
    rms = similarity_rms(layout, local)
    if rms <= tol:
        return
    what = f"{name}: the {pp.plate} plate of configuration {pp.configuration}"
    if similarity_rms(layout, local, mirror=True) <= tol:
        raise InputError(f"{what} is the mirror image of the hole layout (x or y reversed?)")
    raise InputError(
        f"{what} does not have the hole layout ({rms:.1f} mm rms off it): points mislabelled "
        "or another layout"
    )
