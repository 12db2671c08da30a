"""Calibration of camera and projector from the control-point body's six frames.

See ``docs/calibration.md``. The public entry points:

* :func:`load_frames`, :func:`load_control_points`: read the frames and the control points;
* :func:`calibrate_station`: holes → camera → raster lines on the plates → projector, giving a
  :class:`StationCalibration` (the :class:`~rasterserver.optics.Station` plus residuals);
* :func:`store_calibration`: ingest the frames as a calibration acquisition and store the
  result as the station's next immutable calibration version;
* :mod:`rasterserver.calibration.report`: text report and residual plot.
"""

from __future__ import annotations

from rasterserver.calibration.camera_calibration import CameraCalibration, calibrate_camera
from rasterserver.calibration.control_points import ControlPointFile, load_control_points
from rasterserver.calibration.hole_detection import detect_plates
from rasterserver.calibration.projector_calibration import (
    ProjectorCalibration,
    calibrate_projector,
)
from rasterserver.calibration.station_calibration import (
    CalibrationFrames,
    StationCalibration,
    calibrate_station,
    load_frames,
)

__all__ = [
    "CalibrationFrames",
    "CameraCalibration",
    "ControlPointFile",
    "ProjectorCalibration",
    "StationCalibration",
    "calibrate_camera",
    "calibrate_projector",
    "calibrate_station",
    "detect_plates",
    "load_control_points",
    "load_frames",
]
