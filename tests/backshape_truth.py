"""BackShape records built from the simulator's truth, for the tests of what users see of the
analysis (documents, commands, HTTP routes, the report) independently of how well the
analysis plugin finds them.

:func:`truth_backshape` puts the truth of a simulated back (landmarks, spinal line, vertebral
bodies, surface rotation, parameters) into a :class:`BackShape` on the grid of a measured
:class:`Surface`, with a plain finite-difference mean and Gaussian curvature of that grid.
"""

from __future__ import annotations

import json
from functools import lru_cache
from typing import Any

import numpy as np

from rasterserver.records_analysis import LANDMARKS, BackShape
from rasterserver.records_surface import Surface


def monge_curvature(z: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean and Gaussian curvature of the height field ``z`` by central differences.

    Signs as :class:`BackShape`: the camera looks along +Z, so a bump towards it (smaller z)
    has H > 0.
    """
    zy, zx = np.gradient(-z, spacing)
    zyy, zyx = np.gradient(zy, spacing)
    _zxy, zxx = np.gradient(zx, spacing)
    g = 1.0 + zx**2 + zy**2
    mean = ((1 + zx**2) * zyy - 2 * zx * zy * zyx + (1 + zy**2) * zxx) / (2 * g**1.5)
    gauss = (zxx * zyy - zyx**2) / g**2
    return (-mean).astype(np.float32), gauss.astype(np.float32)


def truth_backshape(
    truth: dict[str, Any],
    surface: Surface,
    *,
    spread: float | None = None,
    drop: tuple[str, ...] = (),
    shift: tuple[float, float, float] = (0.0, 0.0, 0.0),
    scale: float = 1.0,
) -> BackShape:
    """A BackShape holding the truth of a simulated back on ``surface``'s grid.

    Parameters
    ----------
    truth : dict
        :func:`rasterserver.simulator.back_truth.truth` of the back.
    surface : Surface
        The measured surface (its grid carries the curvature maps).
    spread : float, optional
        Spread written for every parameter (None: single frame).
    drop : tuple of str, optional
        Landmarks reported as not found (NaN, confidence 0, with a reason).
    shift : (float, float, float), optional
        Added to every position (a patient who swayed between frames), mm.
    scale : float, optional
        Factor on every parameter value.
    """
    offset = np.asarray(shift, dtype=float)
    landmarks = np.array([truth["landmarks"][name] for name in LANDMARKS], dtype=float) + offset
    confidence = np.full(len(LANDMARKS), 0.9)
    reasons = {}
    for name in drop:
        k = LANDMARKS.index(name)
        landmarks[k] = np.nan
        confidence[k] = 0.0
        reasons[name] = "arms over the dimples" if name in ("DL", "DR") else "image cropped"
    spine = truth["spine"]
    skin = np.asarray(spine["skin"], dtype=float) + offset
    body = np.asarray(spine["body"], dtype=float) + offset
    rotation = np.asarray(spine["surface_rotation_deg"], dtype=float)
    vp, dm = landmarks[0], landmarks[3]
    if np.all(np.isfinite(vp)) and np.all(np.isfinite(landmarks[1:4])):
        vertical = (vp - dm) / np.linalg.norm(vp - dm)
        transverse = landmarks[2] - landmarks[1]
        transverse -= vertical * (transverse @ vertical)
        transverse /= np.linalg.norm(transverse)
        axes = np.stack([transverse, vertical, np.cross(transverse, vertical)])
        origin = dm
    else:
        axes, origin = np.full((3, 3), np.nan), np.full(3, np.nan)
    mean, gauss = monge_curvature(surface.z, surface.spacing)
    parameters = {
        name: {"value": scale * p["value"], "unit": p["unit"], "spread": spread}
        for name, p in truth["parameters"].items()
    }
    return BackShape(
        x0=surface.x0,
        y0=surface.y0,
        spacing=surface.spacing,
        mean_curvature=mean,
        gaussian_curvature=gauss,
        landmarks=landmarks,
        landmark_confidence=confidence,
        frame_origin=origin,
        frame_axes=axes,
        symmetry_line=skin,
        surface_rotation=rotation,
        midline=body,
        parameters=json.dumps(parameters, sort_keys=True),
        reasons=json.dumps(reasons, sort_keys=True),
    )


@lru_cache(maxsize=4)
def simulated(preset: str = "moderate", seed: int = 1) -> tuple[Any, Surface, dict[str, Any]]:
    """A rendered back of ``preset``: (image, reconstructed surface, truth); cached."""
    from rasterserver.optics import default_station
    from rasterserver.pipeline import run_chain
    from rasterserver.simulator.back import make_back
    from rasterserver.simulator.back import preset as back_preset
    from rasterserver.simulator.back_truth import truth
    from rasterserver.simulator.render import RenderSettings, render
    from rasterserver.stage import StageContext

    station = default_station()
    scene = make_back(back_preset(preset))
    image = render(scene, station, settings=RenderSettings(supersampling=1), seed=seed).image
    context = StageContext(calibration=station, raster=station.raster_definition)
    surface = run_chain(image, context=context, until="surface")["surface"]
    assert isinstance(surface, Surface)
    return image, surface, truth(scene)
