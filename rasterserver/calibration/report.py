"""Calibration reports: a verdict against bounds, a text report and a residual plot (PNG).

The plot is drawn with OpenCV (matplotlib is not a dependency): the mean of the projector-off
frames, enlarged, with every control point's residual vector magnified so that the bound
(``max_rms_px``) is ``arrow_px`` pixels long, and every used raster line's mean residual as a
coloured tick at its right end (red: above the bound).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rasterserver.calibration.station_calibration import CalibrationFrames, StationCalibration
from rasterserver.errors import InputError

__all__ = ["Bounds", "Verdict", "judge", "plot_residuals", "text_report"]


@dataclass(frozen=True)
class Bounds:
    """Acceptance bounds of a calibration.

    Attributes
    ----------
    max_rms_px : float
        Largest rms control-point reprojection error (px).
    max_point_px : float
        Largest single control-point residual (px).
    max_line_rms_mm : float
        Largest rms residual of the raster peaks across the lines on the plates (mm).
    """

    max_rms_px: float = 0.1
    max_point_px: float = 0.3
    max_line_rms_mm: float = 0.1


@dataclass(frozen=True)
class Verdict:
    """Whether a calibration is within its bounds, with the reasons if not."""

    ok: bool
    reasons: tuple[str, ...]

    def text(self) -> str:
        """One line: ``PASS`` or ``FAIL: reason; reason``."""
        return "PASS" if self.ok else "FAIL: " + "; ".join(self.reasons)


def judge(result: StationCalibration, bounds: Bounds) -> Verdict:
    """Compare a calibration's residuals with ``bounds``."""
    reasons = []
    cam = result.camera
    if not cam.rms <= bounds.max_rms_px:
        reasons.append(f"control points {cam.rms:.3f} px rms > {bounds.max_rms_px:g} px")
    lengths = np.linalg.norm(cam.residuals, axis=1)
    worst = int(np.argmax(lengths))
    if not lengths[worst] <= bounds.max_point_px:
        reasons.append(
            f"control point {result.point_ids[worst]} off by {lengths[worst]:.3f} px "
            f"> {bounds.max_point_px:g} px"
        )
    mm = result.projector_rms_mm
    if not mm <= bounds.max_line_rms_mm:
        reasons.append(f"raster lines {mm:.3f} mm rms > {bounds.max_line_rms_mm:g} mm")
    return Verdict(not reasons, tuple(reasons))


def text_report(result: StationCalibration, verdict: Verdict | None = None) -> str:
    """A plain-text report: parameters, residuals per control point and per plate."""
    st = result.station
    cam, proj = st.camera, st.projector
    lines = [
        f"calibration {st.name}",
        "camera: fx {:.2f} fy {:.2f} cx {:.2f} cy {:.2f} px; distortion {}".format(
            cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2],
            " ".join(f"{d:.5f}" for d in cam.dist),
        ),
        "camera centre (mm): " + " ".join(f"{c:.2f}" for c in cam.centre),
        "projector: f {:.2f} cv {:.2f} units; distortion {}".format(
            proj.K[1, 1], proj.K[1, 2], " ".join(f"{d:.5f}" for d in proj.dist)
        ),
        "projector centre (mm): " + " ".join(f"{c:.2f}" for c in proj.centre)
        + " (x along the lines taken from the reference)",
        f"stereo base: {st.base:.2f} mm",
        "",
        f"control points: {len(result.point_ids)}, reprojection {result.camera.rms:.4f} px rms",
        "  id               u         v        du       dv",
    ]
    for pid, uv, r in zip(result.point_ids, result.point_uv, result.camera.residuals,
                          strict=True):
        lines.append(f"  {pid:<12} {uv[0]:9.3f} {uv[1]:9.3f} {r[0]:8.4f} {r[1]:8.4f}")
    lines += [
        "",
        f"raster peaks: {result.projector.residuals.size} on "
        f"{len(result.line_table)} line pieces, {result.projector.rms:.4f} units = "
        f"{result.projector_rms_mm:.4f} mm rms",
        "  configuration plate  lines  first-last  rms (mm)  worst line (mm)",
    ]
    groups: dict[tuple[int, str], list[dict[str, float]]] = {}
    for row in result.line_table:
        groups.setdefault((int(row["configuration"]), str(row["plate"])), []).append(row)
    for (k, plate), rows in sorted(groups.items()):
        n = np.array([r["peaks"] for r in rows], dtype=float)
        rms = np.array([r["rms_mm"] for r in rows])
        total = float(np.sqrt((n * rms**2).sum() / n.sum()))
        nums = [int(r["number"]) for r in rows]
        lines.append(
            f"  {k:<13} {plate:<6} {len(rows):5d}  {min(nums):3d}-{max(nums):<3d}    "
            f"{total:8.4f}  {rms.max():8.4f}"
        )
    lines += ["", "timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in
                                               result.timings.items())]
    if verdict is not None:
        lines += ["", f"verdict: {verdict.text()}"]
    return "\n".join(lines) + "\n"


def plot_residuals(
    result: StationCalibration,
    frames: CalibrationFrames,
    path: str | Path,
    *,
    bounds: Bounds | None = None,
    zoom: int = 2,
    arrow_px: float = 60.0,
) -> Path:
    """Draw the residual vectors over the image and write a PNG.

    Parameters
    ----------
    result : StationCalibration
    frames : CalibrationFrames
        For the background (mean of the projector-off frames).
    path : str or Path
        PNG to write.
    bounds : Bounds, optional
        The rms bound sets the arrow scale (default 0.1 px) and the tick colours.
    zoom : int
        Enlargement of the image.
    arrow_px : float
        Drawn length (output px) of a residual as large as the bound.

    Returns
    -------
    Path
    """
    bounds = bounds or Bounds()
    background = np.mean([f.astype(np.float32) for f in frames.off.values()], axis=0)
    # OpenCV's stubs make dst required; None (a new array) is what its documentation allows
    grey = cv2.normalize(  # type: ignore[call-overload]
        background, None, 40, 200, cv2.NORM_MINMAX
    ).astype(np.uint8)
    canvas = cv2.cvtColor(
        cv2.resize(grey, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST),
        cv2.COLOR_GRAY2BGR,
    )
    gain = arrow_px / max(bounds.max_rms_px, 1e-9)

    def at(uv: np.ndarray) -> tuple[int, int]:
        # pixel centres sit at (i + 0.5) * zoom in the enlarged image
        return round(float(uv[0] + 0.5) * zoom), round(float(uv[1] + 0.5) * zoom)

    for uv, r in zip(result.point_uv, result.camera.residuals, strict=True):
        start = at(uv)
        colour = (0, 0, 255) if np.linalg.norm(r) > bounds.max_point_px else (0, 200, 255)
        cv2.circle(canvas, start, 3, (0, 255, 0), 1, cv2.LINE_AA)
        cv2.arrowedLine(canvas, start, at(uv + r * gain / zoom), colour, 2, cv2.LINE_AA,
                        tipLength=0.2)
    # raster lines: a tick at each line piece's right end, coloured by its rms
    limit_units = bounds.max_line_rms_mm / max(result.projector_rms_mm, 1e-12) * max(
        result.projector.rms, 1e-12
    )
    pixels = result.line_pixels
    residuals = result.projector.residuals
    for i in range(len(result.line_table)):
        sel = result.line_key == i
        if not np.any(sel):
            continue
        rms = float(np.sqrt(np.mean(residuals[sel] ** 2)))
        end = at(pixels[sel][np.argmax(pixels[sel, 0])])
        colour = (0, 0, 255) if rms > limit_units else (255, 160, 0)
        length = int(min(rms / limit_units, 3.0) * 20) + 2
        cv2.line(canvas, (end[0] + 4, end[1]), (end[0] + 4 + length, end[1]), colour, 2)
    text = (f"control points {result.camera.rms:.3f} px rms (arrow {arrow_px:.0f} px = "
            f"{bounds.max_rms_px:g} px); lines {result.projector_rms_mm:.3f} mm rms")
    cv2.putText(canvas, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                cv2.LINE_AA)
    path = Path(path)
    if not cv2.imwrite(str(path), canvas):
        raise InputError(f"{path}: cannot write the report image (a .png name?)")
    return path
