"""The camera and projector parts of a calibration: the OpenCV pinhole model with distortion
and pose, and the checks that make a device usable (a proper ``K``, a rotation, a lens model
that does not fold back inside the image)."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import ConfigDict, Field, Strict, field_validator, model_validator

from rasterserver.documents.fields import (
    ROTATION_TOL,
    Finite,
    Matrix3,
    Positive,
    StrictDocument,
    Vector3,
    fmt,
    refuse,
    vec,
)


class DeviceDocument(StrictDocument):
    """What camera and projector share: the OpenCV pinhole model with distortion and pose."""

    model: Literal["opencv-pinhole"] = Field(
        "opencv-pinhole", description="the device model; `opencv-pinhole` is the only one so far"
    )
    K: Matrix3 = Field(
        description="intrinsic matrix `[[fx, s, cx], [0, fy, cy], [0, 0, 1]]` in pixels "
        "(camera) or diapositive units (projector); fx, fy > 0 (checked)"
    )
    distortion: Annotated[list[Finite], Field(min_length=4, max_length=14)] = Field(
        [0.0] * 5,
        description="`[k1, k2, p1, p2, k3]`, OpenCV order, acting on normalised coordinates; "
        "4 values (k3 = 0) or OpenCV's 8, 12 or 14 with the terms after k3 zero are accepted; "
        "the lens model must not fold back inside the image (checked)",
    )
    R: Matrix3 = Field(
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        description="rotation world → device: orthonormal with determinant +1 (checked to "
        "1e-6; the nearest rotation is used)",
    )
    t: Vector3 = Field(description="translation world → device, mm: `p_dev = R @ p_world + t`")
    centre: Vector3 | None = Field(
        None,
        description="projection centre in world mm, `-R.T @ t`; written for readers' "
        "convenience, derived when reading (a value that disagrees by over 0.01 mm is refused)",
    )

    @field_validator("K")
    @classmethod
    def _intrinsics(cls, k: list[list[float]]) -> list[list[float]]:
        problems = []
        if not (k[0][0] > 0 and k[1][1] > 0):
            problems.append(
                f"focal lengths must be positive (fx = {fmt(k[0][0])}, fy = {fmt(k[1][1])})"
            )
        if any(abs(v) > 1e-9 for v in (k[1][0], k[2][0], k[2][1])) or abs(k[2][2] - 1) > 1e-9:
            problems.append(
                "must be upper triangular with last row [0, 0, 1] "
                f"(rows 2 and 3 are {vec(k[1])}, {vec(k[2])})"
            )
        if problems:
            raise refuse("; ".join(problems))
        return k

    @field_validator("distortion")
    @classmethod
    def _distortion_terms(cls, dist: list[float]) -> list[float]:
        if len(dist) not in (4, 5, 8, 12, 14):
            raise refuse(
                f"{len(dist)} coefficients; OpenCV uses 4, 5, 8, 12 or 14 "
                "(k1, k2, p1, p2[, k3[, ...]])"
            )
        if any(dist[5:]):
            raise refuse(
                f"only k1, k2, p1, p2, k3 are modelled; coefficients 6 to {len(dist)} must be 0"
            )
        return dist

    @field_validator("R")
    @classmethod
    def _rotation(cls, r: list[list[float]]) -> list[list[float]]:
        rot = np.asarray(r, dtype=np.float64)
        error = float(np.abs(rot @ rot.T - np.eye(3)).max())
        if error > ROTATION_TOL:
            raise refuse(
                f"not a rotation: R @ R.T differs from the identity by {error:.3g} "
                f"(tolerance {ROTATION_TOL:g})"
            )
        if np.linalg.det(rot) < 0:
            raise refuse("a reflection (determinant -1), not a rotation")
        return r

    @model_validator(mode="after")
    def _centre_and_lens(self) -> DeviceDocument:
        if self.centre is not None:
            derived = self.position()
            off = float(np.linalg.norm(np.asarray(self.centre) - derived))
            if off > 0.01:
                raise refuse(
                    f"{vec(self.centre)} is not -R.T @ t = {vec(derived)} (off by "
                    f"{off:.3g} mm); it is derived: correct or remove it",
                    "centre",
                )
        self._check_lens()
        return self

    def rotation(self) -> np.ndarray:
        """``R``, or the nearest proper rotation to it when it is off by more than the devices
        accept (1e-9: a document with rounded decimals)."""
        rot = np.asarray(self.R, dtype=np.float64)
        if np.abs(rot @ rot.T - np.eye(3)).max() <= 1e-9:
            return rot  # exactly as written, so a document round-trips bit for bit
        u, _, vt = np.linalg.svd(rot)
        return u @ vt

    def position(self) -> np.ndarray:
        """The projection centre in world mm, ``-R.T @ t``."""
        return -self.rotation().T @ np.asarray(self.t, dtype=np.float64)

    def coefficients(self) -> np.ndarray:
        """The five coefficients ``(k1, k2, p1, p2, k3)`` of the model."""
        dist = np.zeros(5)
        dist[: min(5, len(self.distortion))] = self.distortion[:5]
        return dist

    def _check_lens(self) -> None:
        """Refuse a radial distortion that folds back inside the image: it has no inverse
        there (``undistort_normalized`` would converge to the wrong branch or not at all)."""
        k1, k2, _, _, k3 = self.coefficients()
        if not (k1 or k2 or k3):
            return
        w, h = float(self.width), float(self.height)  # type: ignore[attr-defined]
        k = np.asarray(self.K, dtype=np.float64)
        corners_u = np.array([-0.5, w - 0.5, -0.5, w - 0.5])
        corners_v = np.array([-0.5, -0.5, h - 0.5, h - 0.5])
        yd = (corners_v - k[1, 2]) / k[1, 1]
        xd = (corners_u - k[0, 2] - k[0, 1] * yd) / k[0, 0]
        reach = float(np.hypot(xd, yd).max())  # distorted radius of the farthest corner
        r = np.linspace(0.0, 4.0 * reach, 4001)
        r2 = r * r
        distorted = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        slope = 1 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3))
        folds = np.flatnonzero(slope <= 0)
        end = folds[0] if folds.size else r.size - 1
        if distorted[: end + 1].max() < reach:
            where = f"folds back at {r[end]:.3g}" if folds.size else "never reaches"
            raise refuse(
                f"the radial model {where} (normalised radius) inside the image, which "
                f"reaches {reach:.3g}: not invertible there",
                "distortion",
            )


class CameraDocument(DeviceDocument):
    """The recording camera, in pixels."""

    model_config = ConfigDict(title="camera")

    width: Annotated[int, Strict(), Field(ge=1, le=100_000)] = Field(
        description="image columns (an integer ≥ 1); a frame must have exactly this size"
    )
    height: Annotated[int, Strict(), Field(ge=1, le=100_000)] = Field(
        description="image rows (an integer ≥ 1)"
    )


class ProjectorDocument(DeviceDocument):
    """The raster projector, an inverse camera, in diapositive units."""

    model_config = ConfigDict(title="projector")

    width: Positive = Field(
        description="extent of the usable diapositive area (units, > 0): valid coordinates "
        "lie in `[-0.5, width - 0.5]`; the renderer sends no light outside it"
    )
    height: Positive = Field(
        description="extent of the usable diapositive area along `v` (units, > 0)"
    )
