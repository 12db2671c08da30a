"""Calibrate a whole station from the seed's six control-point frames.

Per configuration ``k`` of the control-point body there are two frames, recorded without
moving anything but the projector's lamp: ``config<k>-projector-off`` (control points) and
``config<k>-projector-on`` (raster lines). Because the frames are pixel-synchronous, the plate
masks found in the projector-off frame select the raster peaks on the plates in the
projector-on frame (the seed's "image segmentation by storing the image information in
different frames").

Steps: holes in every projector-off frame (:mod:`.control_points`) → which detected plate is
which control plane, by one DLT over all frames (:func:`.camera_calibration.assign_plates`) →
camera adjustment → raster peaks on the plates (the registered ``peaks.first-moment`` stage),
numbered per plate by the code → 3-D points on the plates' planes → projector adjustment
(:mod:`.projector_calibration`).
"""

from __future__ import annotations

import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rasterserver.calibration.camera_calibration import (
    CameraCalibration,
    assign_plates,
    calibrate_camera,
)
from rasterserver.calibration.control_points import ControlPointFile
from rasterserver.calibration.hole_detection import DetectedPlate, detect_plates
from rasterserver.calibration.projector_calibration import (
    ProjectorCalibration,
    calibrate_projector,
    intersect_plane,
    number_plate_lines,
)
from rasterserver.errors import InputError
from rasterserver.optics import Station
from rasterserver.raster import Raster
from rasterserver.records import Image
from rasterserver.records_lines import Peaks

__all__ = [
    "CalibrationFrames",
    "StationCalibration",
    "calibrate_station",
    "load_frames",
]

_FRAME_NAME = re.compile(r"^config(\d+)-projector-(on|off)$")
_FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".npy")

#: A DLT over correctly labelled control points fits to a fraction of a pixel (only the lens
#: distortion is missing from it); mislabelled points are off by tens of pixels.
MAX_DLT_RMS_PX = 2.0
#: As a fraction of the line spacing: a plate numbered one line off misfits by a full spacing.
MAX_PROJECTOR_DLT_RMS = 0.25
#: Gravity in the world frame of a calibration from the control-point body. That frame is the
#: control points' (the camera pose is fitted to them), which ``rasterserver.control_points/1``
#: defines with Y down: the body stands with its plates plumb, so +Y is the vertical.
BODY_GRAVITY = (0.0, 1.0, 0.0)


@dataclass(frozen=True, eq=False)
class CalibrationFrames:
    """The control-point frames by configuration.

    Attributes
    ----------
    off, on : dict of int to numpy.ndarray
        Projector-off and projector-on frames per configuration number.
    names : dict of (int, str) to str
        Where each frame came from, for messages (``(k, "on")`` → file name).
    """

    off: dict[int, np.ndarray]
    on: dict[int, np.ndarray]
    names: dict[tuple[int, str], str] = field(default_factory=dict)


def load_frames(folder: str | Path) -> CalibrationFrames:
    """Read ``config<k>-projector-on|off.(png|tif|npy)`` from a folder.

    Raises
    ------
    InputError
        No such folder or no frames in it; unreadable frames.
    """
    from rasterserver.imageio import read_frame

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: no such folder of calibration frames")
    off: dict[int, np.ndarray] = {}
    on: dict[int, np.ndarray] = {}
    names: dict[tuple[int, str], str] = {}
    for path in sorted(folder.iterdir()):
        match = _FRAME_NAME.match(path.stem)
        if match is None or path.suffix.lower() not in _FRAME_SUFFIXES:
            continue
        k, state = int(match.group(1)), match.group(2)
        if (k, state) in names:
            raise InputError(f"{folder}: two files for {path.stem} ({names[(k, state)]}, "
                             f"{path.name})")
        (on if state == "on" else off)[k] = read_frame(path)
        names[(k, state)] = path.name
    if not names:
        raise InputError(f"{folder}: no config<k>-projector-on/off frames found")
    return CalibrationFrames(off, on, names)


@dataclass(frozen=True, eq=False)
class StationCalibration:
    """A computed calibration with everything needed to judge and store it.

    Attributes
    ----------
    station : Station
        The calibrated station (its ``to_dict()`` is the calibration JSON).
    camera : CameraCalibration
        Camera adjustment with per-point residuals.
    projector : ProjectorCalibration
        Projector adjustment with per-peak residuals.
    point_ids : list of str
        Control-point ids in the order of ``camera.residuals``.
    point_uv : numpy.ndarray
        ``(N, 2)`` measured image positions of the control points.
    point_configuration : numpy.ndarray
        ``(N,)`` configuration of each control point.
    line_table : list of dict
        Per (configuration, plate, line number): peaks, rms ``v`` residual (units, mm).
    line_pixels : numpy.ndarray
        ``(M, 2)`` image positions of the raster peaks used.
    line_configuration : numpy.ndarray
        ``(M,)`` configuration of each raster peak.
    line_key : numpy.ndarray
        ``(M,)`` index of each raster peak's row in ``line_table``.
    timings : dict of str to float
        Seconds per step.
    """

    station: Station
    camera: CameraCalibration
    projector: ProjectorCalibration
    point_ids: list[str]
    point_uv: np.ndarray
    point_configuration: np.ndarray
    line_table: list[dict[str, Any]]
    line_pixels: np.ndarray
    line_configuration: np.ndarray
    line_key: np.ndarray
    timings: dict[str, float]

    @property
    def projector_rms_mm(self) -> float:
        """Rms ``v`` residual as a distance across the lines on the plates (mm)."""
        return self.projector.rms * self._mm_per_unit

    @property
    def _mm_per_unit(self) -> float:
        proj = self.station.projector
        return float(np.linalg.norm(proj.centre)) / float(proj.K[1, 1])

    def residuals_dict(self) -> dict[str, Any]:
        """JSON-ready residuals for the catalogue (``Calibration.residuals``)."""
        cam = self.camera
        res = cam.residuals
        return {
            "camera": {
                "rms_px": cam.rms,
                "max_px": float(np.linalg.norm(res, axis=1).max()),
                "sigma": cam.sigma,
                "points": [
                    {"id": pid, "u": float(uv[0]), "v": float(uv[1]),
                     "du": float(r[0]), "dv": float(r[1])}
                    for pid, uv, r in zip(self.point_ids, self.point_uv, res, strict=True)
                ],
            },
            "projector": {
                "rms_units": self.projector.rms,
                "rms_mm": self.projector_rms_mm,
                "dlt_rms_units": self.projector.dlt_rms,
                "peaks": int(self.projector.residuals.size),
                "sigma": self.projector.sigma,
                "lines": self.line_table,
            },
        }


def _check_frames(frames: CalibrationFrames, control: ControlPointFile) -> list[int]:
    wanted = control.configurations
    problems = []
    for k in wanted:
        for state, have in (("off", frames.off), ("on", frames.on)):
            if k not in have:
                problems.append(f"frame config{k}-projector-{state} is missing")
    for state, have in (("off", frames.off), ("on", frames.on)):
        for k in sorted(set(have) - set(wanted)):
            problems.append(f"frame config{k}-projector-{state} has no control points")
    if problems:
        raise InputError("; ".join(problems))
    if len(wanted) < 2:
        raise InputError("at least two configurations are needed (control points at two depths "
                         "per plate position)")
    shapes = {a.shape for a in (*frames.off.values(), *frames.on.values())}
    if len(shapes) != 1:
        raise InputError(f"the frames differ in size: {sorted(shapes)}")
    return wanted


def _plate_peaks(
    peaks: Peaks, plate: DetectedPlate, *, margin: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    interior = plate.interior(margin=margin, hole_margin=margin)
    rows = np.clip(np.rint(peaks.row).astype(np.int64), 0, interior.shape[0] - 1)
    inside = interior[rows, peaks.col]
    return peaks.col[inside], peaks.row[inside], peaks.area[inside].astype(np.float64)


def calibrate_station(
    frames: CalibrationFrames,
    control: ControlPointFile,
    *,
    raster: Raster,
    reference: Station,
    name: str = "calibrated",
    camera_distortion: Sequence[str] = ("k1",),
    projector_distortion: Sequence[str] = ("k1",),
    peak_params: Mapping[str, Any] | None = None,
    edge_margin: int = 6,
) -> StationCalibration:
    """Calibrate camera and projector from the control-point frames.

    Parameters
    ----------
    frames : CalibrationFrames
        Projector-off and projector-on frame of every configuration.
    control : ControlPointFile
        The control points (world mm) of every plate in every configuration.
    raster : Raster
        The diapositive the projector carries.
    reference : Station
        Nominal design or previous calibration; supplies only what the frames cannot
        determine (the projector's ``u`` direction quantities, diapositive extent).
    name : str
        Name written into the calibration document.
    camera_distortion, projector_distortion : sequence of str
        Distortion terms to estimate.
    peak_params : Mapping, optional
        Parameters of the ``peaks.first-moment`` stage.
    edge_margin : int
        Raster peaks closer than this (px) to a plate edge or hole are not used: their profile
        is cut.

    Returns
    -------
    StationCalibration

    Raises
    ------
    InputError
        A frame missing or extra, a plate not visible, a hole missing or extra, control points
        that do not fit one camera (mislabelled), lines that cannot be numbered.
    """
    from rasterserver.registry import get_registry
    from rasterserver.stage import run_stage

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    configs = _check_frames(frames, control)
    height, width = next(iter(frames.off.values())).shape
    detected: dict[int, list[DetectedPlate]] = {}
    for k in configs:
        fname = frames.names.get((k, "off"), f"config{k}-projector-off")
        expected = len(control.plates[k])
        plates = detect_plates(frames.off[k], layout=control.layout, expected=expected,
                               name=fname)
        if len(plates) != expected:
            raise InputError(
                f"{fname}: found {len(plates)} control plate(s), expected {expected} "
                "(a plate not visible, out of the image or not lit?)"
            )
        detected[k] = plates
    timings["control points"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    observed = [[p.holes for p in detected[k]] for k in configs]
    known = [[pp.xyz for pp in control.plates[k]] for k in configs]
    assignment, dlt_rms, errors = assign_plates(observed, known)
    ids: list[str] = []
    xyz: list[np.ndarray] = []
    uv: list[np.ndarray] = []
    conf: list[int] = []
    for k, perm in zip(configs, assignment, strict=True):
        for i, j in enumerate(perm):
            pp = control.plates[k][j]
            ids.extend(pp.ids)
            xyz.append(pp.xyz)
            uv.append(detected[k][i].holes)
            conf.extend([k] * 7)
    if dlt_rms > MAX_DLT_RMS_PX:
        worst = np.argsort(errors)[::-1][:4]
        listing = ", ".join(f"{ids[i]} ({errors[i]:.1f} px)" for i in worst)
        raise InputError(
            f"the control points do not fit one camera (DLT residual {dlt_rms:.1f} px rms; "
            f"worst {listing}): control points mislabelled or a wrong control-point file"
        )
    xyz_all, uv_all = np.concatenate(xyz), np.concatenate(uv)
    cam = calibrate_camera(
        xyz_all, uv_all, width=width, height=height, distortion=camera_distortion
    )
    timings["camera"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    stage = get_registry().get("peaks.first-moment")
    points: list[np.ndarray] = []
    vs: list[np.ndarray] = []
    pixels: list[np.ndarray] = []
    labels: list[tuple[int, str, np.ndarray]] = []
    for k, perm in zip(configs, assignment, strict=True):
        fname = frames.names.get((k, "on"), f"config{k}-projector-on")
        found = run_stage(stage, Image(frames.on[k]), dict(peak_params or {}))
        assert isinstance(found, Peaks)
        for i, j in enumerate(perm):
            pp = control.plates[k][j]
            col, row, area = _plate_peaks(found, detected[k][i], margin=edge_margin)
            lines = number_plate_lines(
                col, row, area, raster, name=f"{fname}: {pp.plate} plate"
            )
            normal, offset = pp.plane()
            points.append(intersect_plane(cam.camera, lines.pixels, normal, offset))
            vs.append(lines.v)
            pixels.append(lines.pixels)
            labels.append((k, pp.plate, lines.number))
    xyz_lines, v_lines = np.concatenate(points), np.concatenate(vs)
    timings["raster peaks"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    proj = calibrate_projector(
        xyz_lines, v_lines, reference=reference.projector, distortion=projector_distortion
    )
    if proj.dlt_rms > MAX_PROJECTOR_DLT_RMS * raster.spacing:
        raise InputError(
            f"the raster lines on the plates do not fit one projector (linear fit off by "
            f"{proj.dlt_rms:.2f} units rms, line spacing {raster.spacing:g}): a plate's lines "
            "numbered wrongly"
        )
    timings["projector"] = time.perf_counter() - t0

    station = Station(
        camera=cam.camera, projector=proj.projector, raster=raster, name=name,
        gravity=np.array(BODY_GRAVITY),
    )
    mm_per_unit = float(np.linalg.norm(proj.projector.centre)) / float(proj.projector.K[1, 1])
    table: list[dict[str, Any]] = []
    keys: list[np.ndarray] = []
    start = 0
    for k, plate, numbers in labels:
        res = proj.residuals[start : start + numbers.size]
        start += numbers.size
        key = np.empty(numbers.size, np.int64)
        for number in np.unique(numbers):
            key[numbers == number] = len(table)
            r = res[numbers == number]
            rms = float(np.sqrt(np.mean(r**2)))
            table.append({"configuration": k, "plate": plate, "number": int(number),
                          "peaks": int(r.size), "rms_units": rms, "rms_mm": rms * mm_per_unit,
                          "mean_units": float(r.mean())})
        keys.append(key)
    line_conf = np.concatenate([np.full(n.size, k) for k, _, n in labels])
    return StationCalibration(
        station=station,
        camera=cam,
        projector=proj,
        point_ids=ids,
        point_uv=uv_all,
        point_configuration=np.asarray(conf),
        line_table=table,
        line_pixels=np.concatenate(pixels),
        line_configuration=line_conf,
        line_key=np.concatenate(keys),
        timings=timings,
    )
