"""Writing results for other programs: point clouds, meshes and the line overlay image.

* Point clouds as PLY (binary, open3d's tensor point cloud: ``x, y, z`` as doubles plus the
  per-point properties ``number`` and ``col`` (int), ``row`` (double) and ``area`` (float),
  which any PLY reader lists as vertex properties) or CSV (one header line, one point per
  line).
* Meshes as PLY, OBJ or STL through ``open3d.io.write_triangle_mesh``; vertex normals face
  the camera.
* The overlay: the raw frame with every peak coloured by its line number and the numbers
  written at the ends of each line, what a clinician looks at to trust the numbering.

Coordinates are millimetres, in one of two frames (:class:`ExportFrame`):

* ``station`` (default): the world frame of the calibration used — X to the patient's right,
  Y down (gravity), Z away from the camera (anterior);
* ``patient``: the body-fixed frame of the acquisition's back-shape analysis (origin DM, the
  midpoint of the lumbar dimples; X transverse towards the patient's right along DL→DR, Y up
  along DM→VP, Z posterior, right-handed; ``docs/analysis.md``), the frame in which visits are
  compared. It needs VP, DL, DR and DM; an acquisition without them is refused with the reason.

Every file written by ``rasterserver export`` gets a sidecar ``<file>.json`` naming the
acquisition, the stored result, the frame with its origin and axes, and the units.
"""

from __future__ import annotations

import colorsys
import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import cv2
import numpy as np

from rasterserver.errors import InputError
from rasterserver.export_choices import ExportFormat, ExportFrame, ExportWhat
from rasterserver.output_files import check_output, output_file
from rasterserver.records import Record
from rasterserver.records_surface import MeshRecord, Points, Surface

# ExportFormat, ExportWhat and ExportFrame live in rasterserver.export_choices so that the
# command line can build its options without NumPy and OpenCV; they are re-exported here.

if TYPE_CHECKING:
    import open3d as o3d

    from rasterserver.catalog.models import StageResult
    from rasterserver.pipeline import Pipeline

__all__ = [
    "MESH_FORMATS",
    "POINT_FORMATS",
    "ExportFormat",
    "ExportFrame",
    "ExportWhat",
    "StoredExport",
    "line_colours",
    "overlay_image",
    "select_export",
    "write_mesh",
    "write_points",
]

POINT_FORMATS = ("ply", "csv")
MESH_FORMATS = ("ply", "obj", "stl")

_GOLDEN = 0.618033988749895


_STAGE_OF = {ExportWhat.mesh: "mesh", ExportWhat.points: "points", ExportWhat.smoothed: "surface"}

SIDECAR_FORMAT = "rasterserver.export/1"

_FRAME_AXES = {
    ExportFrame.station: "X to the patient's right, Y down (gravity), Z anterior (away from "
    "the camera): the calibration's world frame",
    ExportFrame.patient: "origin DM; X to the patient's right (DL->DR), Y up (DM->VP), Z "
    "posterior; right-handed body-fixed frame of the back-shape analysis",
}


@dataclass(frozen=True)
class StoredExport:
    """A stored result chosen for export: its provenance row and the record to write."""

    row: StageResult
    record: MeshRecord | Points
    fmt: ExportFormat
    what: ExportWhat
    uid: str = ""
    frame: ExportFrame = ExportFrame.station
    #: world → frame: ``p_frame = axes @ (p_world - origin)``; identity for the station frame
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axes: tuple[tuple[float, float, float], ...] = (
        (1.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        (0.0, 0.0, 1.0),
    )
    frame_source: int | None = None

    def write(self, path: Path, *, sidecar: bool = False) -> Path:
        """Write the record to ``path`` in the chosen format, and ``<path>.json`` if asked."""
        if sidecar:
            check_output(sidecar_path(path))
        if isinstance(self.record, MeshRecord):
            write_mesh(self.record, path, fmt=self.fmt.value)  # type: ignore[arg-type]
        else:
            write_points(self.record, path, fmt=self.fmt.value)  # type: ignore[arg-type]
        if sidecar:
            with output_file(sidecar_path(path)) as temp:
                temp.write_text(json.dumps(self.describe(), indent=2) + "\n", encoding="utf-8")
        return path

    def describe(self) -> dict[str, Any]:
        """What the file holds: acquisition, stored result, frame, units (the sidecar)."""
        return {
            "format": SIDECAR_FORMAT,
            "acquisition": self.uid,
            "result": {
                "id": self.row.id,
                "stage": self.row.stage,
                "plugin": self.row.plugin,
                "plugin_version": self.row.plugin_version,
                "output_checksum": self.row.output_checksum,
                "frame_index": self.row.frame_index,
            },
            "what": self.what.value,
            "units": "mm",
            "frame": {
                "name": self.frame.value,
                "axes": _FRAME_AXES[self.frame],
                "origin_world_mm": list(self.origin),
                "axes_in_world": [list(a) for a in self.axes],
                "from_analysis_result": self.frame_source,
            },
        }


def sidecar_path(path: Path) -> Path:
    """The sidecar of an export file: ``back.ply`` → ``back.ply.json``."""
    return Path(path).with_name(Path(path).name + ".json")


def select_export(
    pipeline: Pipeline,
    uid: str,
    *,
    fmt: ExportFormat,
    what: ExportWhat | None = None,
    plugin: str | None = None,
    frame: ExportFrame = ExportFrame.station,
) -> StoredExport:
    """Choose the newest stored mesh or point cloud of ``uid`` for export as ``fmt``.

    The one implementation behind ``rasterserver export`` and the HTTP export route.

    Parameters
    ----------
    pipeline : Pipeline
        The pipeline of the archive holding the results.
    uid : str
        Acquisition uid.
    fmt : ExportFormat
        ``ply``, ``obj``, ``stl`` (meshes) or ``csv`` (points).
    what : ExportWhat, optional
        ``mesh`` (default), ``points`` (one per peak) or ``smoothed``; ``points`` for csv.
    plugin : str, optional
        Use the newest result of this plugin.
    frame : ExportFrame, optional
        ``station`` (the calibration's world frame) or ``patient`` (the body-fixed frame of
        the acquisition's back-shape analysis of the same frame).

    Returns
    -------
    StoredExport

    Raises
    ------
    InputError
        The format cannot hold what is asked, the stored result holds nothing to write, or
        (``patient``) the analysis found no body-fixed frame (the reason is given).
    NotFoundError
        The acquisition has no such stored result (or, ``patient``, no stored analysis).
    """
    what = what or (ExportWhat.points if fmt is ExportFormat.csv else ExportWhat.mesh)
    if what is ExportWhat.mesh and fmt is ExportFormat.csv:
        raise InputError("csv holds points: export points or smoothed, or use a mesh format")
    if what is not ExportWhat.mesh and fmt in (ExportFormat.obj, ExportFormat.stl):
        raise InputError(f"{fmt.value} holds meshes: use ply or csv for points")
    stage = _STAGE_OF[what]
    row, record = pipeline.result(uid, stage, plugin=plugin)
    chosen = StoredExport(row, _exportable(record, uid, stage), fmt, what, uid=uid)
    if frame is ExportFrame.station:
        return chosen
    return _in_patient_frame(pipeline, chosen)


def _in_patient_frame(pipeline: Pipeline, chosen: StoredExport) -> StoredExport:
    """``chosen`` moved into the body-fixed frame of its frame's newest analysis."""
    from rasterserver.records_analysis import FRAME_LANDMARKS, BackShape

    a_row, shape = pipeline.result(chosen.uid, "analysis")
    if not isinstance(shape, BackShape):
        raise InputError(f"the stored analysis of {chosen.uid} is a {shape.kind} record")
    if a_row.frame_index != chosen.row.frame_index:
        raise InputError(
            f"the newest analysis of {chosen.uid} is of frame {a_row.frame_index}, the "
            f"{chosen.row.stage} of frame {chosen.row.frame_index}: process the acquisition "
            "again to analyse the same frame"
        )
    origin, axes = np.asarray(shape.frame_origin), np.asarray(shape.frame_axes)
    if not (np.all(np.isfinite(origin)) and np.all(np.isfinite(axes))):
        missing = {k: v for k, v in shape.reason_table().items() if k in FRAME_LANDMARKS}
        why = "; ".join(f"{k}: {v}" for k, v in missing.items()) or shape.reason or "not found"
        raise InputError(
            f"acquisition {chosen.uid} has no body-fixed frame (it needs VP, DL, DR and DM): {why}"
        )
    return dataclasses.replace(
        chosen,
        record=to_frame(chosen.record, origin, axes),
        frame=ExportFrame.patient,
        origin=_triple(origin),
        axes=tuple(_triple(a) for a in axes),
        frame_source=a_row.id,
    )


def _triple(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def to_frame(
    record: MeshRecord | Points, origin: np.ndarray, axes: np.ndarray
) -> MeshRecord | Points:
    """Move a mesh or point cloud into a frame: ``p_frame = axes @ (p_world - origin)``.

    Parameters
    ----------
    record : MeshRecord or Points
        In world coordinates (mm).
    origin : numpy.ndarray
        ``(3,)`` the frame's origin in world mm.
    axes : numpy.ndarray
        ``(3, 3)`` rows are the frame's unit axes in world coordinates (a rotation).

    Returns
    -------
    MeshRecord or Points
        A new record of the same type; normals are rotated, not moved.
    """
    if isinstance(record, MeshRecord):
        return dataclasses.replace(
            record,
            vertices=(record.vertices - origin) @ axes.T,
            normals=record.normals @ axes.T,
        )
    moved = (record.xyz - origin) @ axes.T
    return dataclasses.replace(
        record,
        x=np.ascontiguousarray(moved[:, 0]),
        y=np.ascontiguousarray(moved[:, 1]),
        z=np.ascontiguousarray(moved[:, 2]),
    )


def _exportable(record: Record, uid: str, stage: str) -> MeshRecord | Points:
    if isinstance(record, Surface):
        samples = record.sample_points()
        if samples is None:
            raise InputError(f"the stored surface of {uid} keeps no smoothed points")
        return samples
    if not isinstance(record, MeshRecord | Points):
        raise InputError(f"the stored {stage} result is a {record.kind} record, not exportable")
    return record


def write_points(points: Points, path: Path, *, fmt: Literal["ply", "csv"] = "ply") -> Path:
    """Write a point cloud with its per-point properties.

    Parameters
    ----------
    points : Points
        The points; must not be empty.
    path : Path
        Target file (overwritten).
    fmt : {"ply", "csv"}
        File format.

    Returns
    -------
    Path

    Raises
    ------
    InputError
        No points (the message carries the record's reason), an unknown format, or a path
        that cannot be written (:func:`rasterserver.output_files.check_output`). The file is
        replaced whole or not at all.
    """
    path = check_output(path)
    if len(points) == 0:
        raise InputError(f"no points to write: {points.reason or 'empty result'}")
    if fmt not in POINT_FORMATS:
        raise InputError(f"unknown point format {fmt!r}; use one of {', '.join(POINT_FORMATS)}")
    if fmt == "ply" and path.suffix.lower() != ".ply":
        # open3d picks the writer from the suffix
        raise InputError(f"{path.name}: a ply file must end in .ply")
    with output_file(path) as temp:
        if fmt == "csv":
            table = np.column_stack(
                [points.x, points.y, points.z, points.number, points.col, points.row, points.area]
            )
            np.savetxt(
                temp,
                table,
                delimiter=",",
                header="x_mm,y_mm,z_mm,line_number,column,row,peak_area",
                comments="",
                fmt=["%.6f", "%.6f", "%.6f", "%d", "%d", "%.6f", "%.4f"],
            )
        else:
            _write_ply_points(points, temp)
    return path


def _write_ply_points(points: Points, path: Path) -> None:
    import open3d as o3d  # here, not at the top: the CLI starts a second faster without it

    cloud = o3d.t.geometry.PointCloud(_tensor(np.ascontiguousarray(points.xyz)))
    for name, values, dtype in (
        ("number", points.number, np.int32),
        ("col", points.col, np.int32),
        ("row", points.row, np.float64),
        ("area", points.area, np.float32),
    ):
        cloud.point[name] = _tensor(np.ascontiguousarray(values, dtype=dtype)[:, None])
    # open3d picks the writer from the suffix, which a temporary name keeps
    if not o3d.t.io.write_point_cloud(path, cloud, write_ascii=False):
        raise OSError(f"open3d could not write {path.name}")


def _tensor(array: np.ndarray) -> o3d.core.Tensor:
    """An open3d tensor holding a copy of ``array`` (its dtype, on the CPU)."""
    import open3d as o3d

    # open3d's generated stubs drop the defaults (None) of dtype and device
    return o3d.core.Tensor(array)  # type: ignore[call-overload]


def write_mesh(mesh: MeshRecord, path: Path, *, fmt: Literal["ply", "obj", "stl"] = "ply") -> Path:
    """Write a triangle mesh with vertex normals.

    Parameters
    ----------
    mesh : MeshRecord
        The mesh; must not be empty.
    path : Path
        Target file (overwritten).
    fmt : {"ply", "obj", "stl"}
        File format (STL keeps only triangles and their normals).

    Returns
    -------
    Path

    Raises
    ------
    InputError
        An empty mesh (with its reason), an unknown format, or a path that cannot be written.
        The file is replaced whole or not at all.
    """
    path = check_output(path)
    if fmt not in MESH_FORMATS:
        raise InputError(f"unknown mesh format {fmt!r}; use one of {', '.join(MESH_FORMATS)}")
    if len(mesh.triangles) == 0:
        raise InputError(f"no mesh to write: {mesh.reason or 'empty result'}")
    if path.suffix.lower() != f".{fmt}":
        # open3d picks the writer from the suffix
        raise InputError(f"{path.name}: a {fmt} file must end in .{fmt}")
    import open3d as o3d

    o3d_mesh: Any = mesh.to_open3d()
    o3d_mesh.compute_triangle_normals()
    with output_file(path) as temp:
        if not o3d.io.write_triangle_mesh(temp, o3d_mesh, write_ascii=False):
            raise OSError(f"open3d could not write {path}")
    return path


def line_colours(numbers: np.ndarray) -> np.ndarray:
    """Distinct BGR colours (uint8) for line numbers: neighbouring lines differ in hue."""
    numbers = np.asarray(numbers)
    out = np.zeros((numbers.size, 3), dtype=np.uint8)
    for i, n in enumerate(numbers.ravel()):
        hue = (float(n) * _GOLDEN) % 1.0
        r, g, b = colorsys.hsv_to_rgb(hue, 0.85, 1.0)
        out[i] = (int(255 * b), int(255 * g), int(255 * r))
    return out


def _to_bgr8(image: np.ndarray) -> np.ndarray:
    frame = np.asarray(image)
    if frame.dtype != np.uint8:
        top = float(frame.max()) or 1.0
        frame = np.clip(frame.astype(np.float64) * (255.0 / top), 0, 255).astype(np.uint8)
    return cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)


def overlay_image(
    image: np.ndarray, lines: Any, *, scale: int = 2, min_label: int = 10, reasons: bool = True
) -> np.ndarray:
    """The frame with its detected lines coloured by number and numbered at their ends, and
    under it why the unnumbered ones are not numbered.

    Parameters
    ----------
    image : numpy.ndarray
        The raw 2-D frame (``uint8`` or ``uint16``, shown scaled to its maximum).
    lines : NumberedLines
        Per-peak ``col``, ``row``, ``number`` and ``line_id`` (``-1``: none).
    scale : int, optional
        Enlargement, so that the numbers are legible next to lines ~10 px apart.
    min_label : int, optional
        Pieces of lines with fewer peaks are coloured but not labelled (less clutter).
    reasons : bool, optional
        Print the numbering's reasons for what it left unnumbered (``lines.reason``, one
        per line of text) in a panel under the frame; none when the reason is empty.

    Returns
    -------
    numpy.ndarray
        ``(scale * H + panel, scale * W, 3)`` BGR ``uint8`` image. Numbered peaks are drawn
        in their line's colour, unnumbered ones in grey; each numbered line (each connected
        piece, by ``line_id``, of at least ``min_label`` peaks) carries its number at both
        ends.
    """
    if scale < 1:
        raise InputError("the overlay scale must be at least 1")
    base = _to_bgr8(image)
    # dim the frame so that the coloured lines stand out against the bright raster
    canvas = cv2.resize(base // 2, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    h, w = canvas.shape[:2]
    col = np.asarray(lines.col, dtype=np.float64)
    row = np.asarray(lines.row, dtype=np.float64)
    number = np.asarray(lines.number)
    line_id = np.asarray(getattr(lines, "line_id", np.full(number.shape, -1)))
    ok = np.isfinite(row)
    x = np.clip(np.rint((col + 0.5) * scale - 0.5).astype(np.int64), 0, w - 1)
    y = np.clip(np.rint((row + 0.5) * scale - 0.5).astype(np.int64), 0, h - 1)
    numbered = ok & (number >= 0)
    unnumbered = ok & (number < 0)
    canvas[y[unnumbered], x[unnumbered]] = (150, 150, 150)
    if numbered.any():
        values, inverse = np.unique(number[numbered], return_inverse=True)
        colours = line_colours(values)[inverse]
        for dy in range(scale):
            canvas[np.minimum(y[numbered] + dy, h - 1), x[numbered]] = colours
    font = cv2.FONT_HERSHEY_SIMPLEX
    size = 0.32 * scale
    for piece in np.unique(line_id[numbered]) if numbered.any() else []:
        sel = np.flatnonzero(numbered & (line_id == piece))
        if piece < 0 or sel.size < min_label:
            continue
        n = int(np.bincount(number[sel] - number[sel].min()).argmax() + number[sel].min())
        colour = tuple(int(c) for c in line_colours(np.array([n]))[0])
        text = str(n)
        (tw, th), _ = cv2.getTextSize(text, font, size, 1)
        left, right = sel[np.argmin(col[sel])], sel[np.argmax(col[sel])]
        for end, dx in ((left, -tw - 3), (right, 3)):
            px = int(np.clip(x[end] + dx, 0, max(w - tw, 0)))
            py = int(np.clip(y[end] + th // 2, th, h - 1))
            cv2.putText(canvas, text, (px, py), font, size, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(canvas, text, (px, py), font, size, colour, 1, cv2.LINE_AA)
    reason = str(getattr(lines, "reason", "") or "") if reasons else ""
    return _with_reasons(canvas, reason) if reason else canvas


def _with_reasons(canvas: np.ndarray, reason: str) -> np.ndarray:
    """``canvas`` with a white panel under it listing the ``"; "``-separated reasons, each
    wrapped to the canvas's width (the overlay is where a refusal must be seen)."""
    font, size, step = cv2.FONT_HERSHEY_SIMPLEX, 0.45, 18
    width = canvas.shape[1]
    rows: list[str] = ["Left unnumbered, and why:"]
    for item in (part.strip() for part in reason.split(";")):
        if not item:
            continue
        words, line = item.split(), "- "
        for word in words:
            trial = f"{line}{word} "
            if cv2.getTextSize(trial, font, size, 1)[0][0] > width - 16 and line.strip("- "):
                rows.append(line.rstrip())
                line = f"  {word} "
            else:
                line = trial
        rows.append(line.rstrip())
    panel = np.full((step * len(rows) + 12, width, 3), 255, dtype=np.uint8)
    for k, text in enumerate(rows):
        cv2.putText(panel, text, (8, step * (k + 1)), font, size, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([canvas, panel])
