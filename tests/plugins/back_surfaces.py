"""Simulated backs through the whole reconstruction chain, with their truth, for the analysis tests.

A surface takes a few seconds to render and reconstruct, so each is made once per test process
(``lru_cache``). The truth is :func:`rasterserver.simulator.back_truth.truth` of the same
scene: the analysis is always compared with what the back truly is, never with an earlier
output of the analysis itself.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
from image_truth import station

from rasterserver.pipeline import run_chain
from rasterserver.records_surface import Surface
from rasterserver.simulator.back import make_back, preset
from rasterserver.simulator.back_truth import truth
from rasterserver.simulator.render import RenderSettings, render
from rasterserver.stage import StageContext

#: Gravity of the simulated station (the world's +Y is plumb).
GRAVITY = np.array([0.0, 1.0, 0.0])


@lru_cache(maxsize=4)
def back(name: str) -> tuple[Surface, dict[str, Any]]:
    """The smoothed surface of preset ``name`` (default noise, seed 1) and its truth."""
    st = station()
    scene = make_back(preset(name))
    rendering = render(scene, st, settings=RenderSettings(supersampling=1), seed=1)
    records = run_chain(
        rendering.image,
        context=StageContext(calibration=st, raster=st.raster_definition),
        until="surface",
    )
    surface = records["surface"]
    assert isinstance(surface, Surface)
    return surface, truth(scene)


def with_z(surface: Surface, z: np.ndarray) -> Surface:
    """``surface`` with its depths replaced (same grid)."""
    return Surface(x0=surface.x0, y0=surface.y0, spacing=surface.spacing, z=z)


def mirrored(surface: Surface) -> Surface:
    """The mirror image of ``surface`` about the world's Y–Z plane (x → −x)."""
    nx = surface.z.shape[1]
    x0 = -(surface.x0 + (nx - 1) * surface.spacing)
    return Surface(x0=x0, y0=surface.y0, spacing=surface.spacing, z=surface.z[:, ::-1].copy())
