"""Camera calibration from control points on planes at two depths.

The camera does not move between the configurations; the body does, but every control point's
coordinates are given in the world frame, so all frames' points form one non-coplanar set seen
by one camera pose. Two steps:

1. a direct linear transformation (DLT, Hartley-normalised) gives the 3 x 4 projection matrix,
   decomposed (RQ) into ``K``, ``R``, ``t``: the start, and the test that tells the plates
   apart (:func:`assign_plates`) and catches mislabelled control points;
2. a bundle adjustment (``scipy.optimize.least_squares``) over the interior orientation
   (``fx``, ``fy``, ``cx``, ``cy``, the chosen distortion terms) and the exterior orientation
   (rotation vector, ``t``) minimises the image residuals with the station's own projection
   (:meth:`rasterserver.optics.Camera.project`).

Which distortion terms are free is a choice: with ~40 points at two depths over ~80 % of the
field, ``k1`` is well determined, ``k2``/``k3`` and the tangential terms are not (they trade
off against the principal point), so by default only ``k1`` is estimated.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.linalg
from scipy.optimize import least_squares

from rasterserver.errors import InputError
from rasterserver.optics import Camera

__all__ = [
    "DISTORTION_TERMS",
    "CameraCalibration",
    "assign_plates",
    "calibrate_camera",
    "decompose_projection",
    "dlt",
]

#: Names of the OpenCV distortion coefficients, in order.
DISTORTION_TERMS = ("k1", "k2", "p1", "p2", "k3")


def _normaliser(points: np.ndarray) -> np.ndarray:
    """Similarity moving the points' centroid to 0 and their rms distance to sqrt(dim)."""
    dim = points.shape[1]
    centre = points.mean(axis=0)
    scale = np.sqrt(dim) / max(np.sqrt(((points - centre) ** 2).sum(axis=1).mean()), 1e-12)
    t = np.eye(dim + 1)
    t[:dim, :dim] *= scale
    t[:dim, dim] = -scale * centre
    return t


def dlt(xyz: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """3 x 4 projection matrix from >= 6 non-coplanar 3-D points and their images.

    Parameters
    ----------
    xyz : numpy.ndarray
        ``(N, 3)`` world points.
    uv : numpy.ndarray
        ``(N, 2)`` image points.

    Returns
    -------
    numpy.ndarray
        ``(3, 4)`` ``P`` with ``uv ~ P @ [xyz, 1]``, scaled so that ``||P[2, :3]|| = 1``.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    if xyz.shape[0] < 6:
        raise InputError(f"a camera needs at least 6 control points, got {xyz.shape[0]}")
    t3, t2 = _normaliser(xyz), _normaliser(uv)
    xh = np.column_stack([xyz, np.ones(len(xyz))]) @ t3.T
    uh = np.column_stack([uv, np.ones(len(uv))]) @ t2.T
    n = len(xyz)
    a = np.zeros((2 * n, 12))
    a[0::2, 0:4] = xh
    a[0::2, 8:12] = -uh[:, :1] * xh
    a[1::2, 4:8] = xh
    a[1::2, 8:12] = -uh[:, 1:2] * xh
    _, s, vt = np.linalg.svd(a)
    if s[-2] < 1e-9 * s[0]:
        raise InputError("the control points do not determine the camera (all on one plane?)")
    p = np.linalg.inv(t2) @ vt[-1].reshape(3, 4) @ t3
    return p / np.linalg.norm(p[2, :3])


def decompose_projection(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split ``P = K [R | t]`` (RQ decomposition) with a positive diagonal of ``K``.

    Returns
    -------
    K, R, t : numpy.ndarray
        ``(3, 3)`` upper-triangular ``K`` with ``K[2, 2] = 1``, rotation ``R``, ``(3,)`` ``t``.
    """
    m = p[:, :3]
    if np.linalg.det(m) < 0:  # the points must lie in front of the camera
        p = -p
        m = -m
    k, r = scipy.linalg.rq(m)
    signs = np.diag(np.sign(np.diag(k)))
    k, r = k @ signs, signs @ r
    t = np.linalg.solve(k, p[:, 3])
    scale = k[2, 2]
    return k / scale, r, t


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """The adjusted camera with its residuals.

    Attributes
    ----------
    camera : Camera
        Interior and exterior orientation.
    residuals : numpy.ndarray
        ``(N, 2)`` image residuals measured minus projected (px), per control point.
    rms : float
        Rms of the residual vector lengths (px).
    sigma : dict
        Standard deviations of the adjusted parameters (from the Jacobian), by name.
    free : tuple of str
        Names of the adjusted parameters.
    """

    camera: Camera
    residuals: np.ndarray
    rms: float
    sigma: dict[str, float]
    free: tuple[str, ...]


def _camera_from(params: np.ndarray, free_dist: Sequence[int], width: int, height: int) -> Camera:
    fx, fy, cx, cy = params[:4]
    dist = np.zeros(5)
    dist[list(free_dist)] = params[4 : 4 + len(free_dist)]
    rvec = params[4 + len(free_dist) : 7 + len(free_dist)]
    t = params[7 + len(free_dist) : 10 + len(free_dist)]
    rot, _ = cv2.Rodrigues(rvec)
    return Camera(
        K=np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]),
        dist=dist, R=rot, t=t, width=width, height=height,
    )


def calibrate_camera(
    xyz: np.ndarray,
    uv: np.ndarray,
    *,
    width: int,
    height: int,
    distortion: Sequence[str] = ("k1",),
) -> CameraCalibration:
    """Interior and exterior orientation from control points (DLT, then bundle adjustment).

    Parameters
    ----------
    xyz : numpy.ndarray
        ``(N, 3)`` control points (world mm), not all on one plane.
    uv : numpy.ndarray
        ``(N, 2)`` their measured image positions (px).
    width, height : int
        Image size (px).
    distortion : sequence of str
        Distortion terms to estimate (of ``k1, k2, p1, p2, k3``); the others stay 0.

    Returns
    -------
    CameraCalibration

    Raises
    ------
    InputError
        Too few or coplanar points, an unknown distortion term, or a failed adjustment.
    """
    unknown = sorted(set(distortion) - set(DISTORTION_TERMS))
    if unknown:
        raise InputError(f"unknown distortion terms {unknown}; choose from {DISTORTION_TERMS}")
    free_dist = [DISTORTION_TERMS.index(d) for d in DISTORTION_TERMS if d in distortion]
    xyz = np.asarray(xyz, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    n_free = 10 + len(free_dist)
    if 2 * len(xyz) < n_free + 4:
        raise InputError(f"{len(xyz)} control points are too few for {n_free} camera parameters")
    k, r, t = decompose_projection(dlt(xyz, uv))
    rvec, _ = cv2.Rodrigues(r)
    start = np.concatenate(
        [[k[0, 0], k[1, 1], k[0, 2], k[1, 2]], np.zeros(len(free_dist)), rvec.ravel(), t]
    )

    def residual(params: np.ndarray) -> np.ndarray:
        cam = _camera_from(params, free_dist, width, height)
        return (cam.project(xyz) - uv).ravel()

    # scale parameters for the solver: pixels, radians, mm behave alike after x_scale="jac"
    fit = least_squares(residual, start, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12)
    if not np.all(np.isfinite(fit.fun)):
        raise InputError("camera adjustment failed: control points behind the camera?")
    camera = _camera_from(fit.x, free_dist, width, height)
    res = fit.fun.reshape(-1, 2)
    rms = float(np.sqrt((res**2).sum(axis=1).mean()))
    names = ("fx", "fy", "cx", "cy", *(DISTORTION_TERMS[i] for i in free_dist),
             "rx", "ry", "rz", "tx", "ty", "tz")
    dof = max(res.size - len(fit.x), 1)
    s2 = float((fit.fun**2).sum() / dof)
    try:
        jac = np.asarray(fit.jac)  # dense with method "lm" (the stubs allow sparse too)
        cov = np.linalg.inv(jac.T @ jac) * s2
        sigma = {nm: float(np.sqrt(max(cov[i, i], 0.0))) for i, nm in enumerate(names)}
    except np.linalg.LinAlgError:
        sigma = {nm: float("nan") for nm in names}
    return CameraCalibration(camera, -res, rms, sigma, names)


def assign_plates(
    observed: Sequence[Sequence[np.ndarray]],
    known: Sequence[Sequence[np.ndarray]],
) -> tuple[list[tuple[int, ...]], float, np.ndarray]:
    """Decide which detected plate is which known plate, frame by frame, by one DLT.

    Every combination of per-frame assignments is tried (two plates in three frames: 8); the
    one whose points fit one projection matrix best wins. A wrong assignment misplaces whole
    plates by tens of pixels, so the choice is clear; if even the best fit is poor the control
    points themselves are wrong (mislabelled), which the caller reports from ``errors``.

    Parameters
    ----------
    observed : sequence of sequence of numpy.ndarray
        Per frame, the detected plates' ``(7, 2)`` image points.
    known : sequence of sequence of numpy.ndarray
        Per frame, the known plates' ``(7, 3)`` world points (same count as ``observed``).

    Returns
    -------
    assignment : list of tuple of int
        Per frame, ``assignment[f][i]`` is the known plate shown by detected plate ``i``.
    rms : float
        DLT residual rms (px) of the chosen assignment.
    errors : numpy.ndarray
        ``(N,)`` DLT residual length per point of the chosen assignment, in the order
        frame, detected plate, hole.
    """
    options = [list(itertools.permutations(range(len(k)))) for k in known]
    best: tuple[float, list[tuple[int, ...]], np.ndarray] | None = None
    for combo in itertools.product(*options):
        uv = np.concatenate([o[i] for o, perm in zip(observed, combo, strict=True)
                             for i in range(len(perm))])
        xyz = np.concatenate([k[perm[i]] for k, perm in zip(known, combo, strict=True)
                              for i in range(len(perm))])
        p = dlt(xyz, uv)
        proj = np.column_stack([xyz, np.ones(len(xyz))]) @ p.T
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.linalg.norm(proj[:, :2] / proj[:, 2:3] - uv, axis=1)
        rms = float(np.sqrt(np.nanmean(err**2)))
        if best is None or rms < best[0]:
            best = (rms, list(combo), err)
    assert best is not None
    return best[1], best[0], best[2]
