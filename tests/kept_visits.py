"""Visits of kept clinic frames (``tests/data/scenes``): the chain run here on frames rendered
once, so that every processor sees the same pixels."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rasterserver.comparison import Visit
from rasterserver.optics import Station
from rasterserver.records_analysis import BackShape
from rasterserver.records_surface import MeshRecord, Surface

KEPT = Path(__file__).parent / "data" / "scenes"


def kept_visit(
    name: str, label: str, params: dict[str, dict[str, object]] | None = None
) -> tuple[Visit, Station]:
    """The Visit of kept frame ``name`` (``person-44-A``: its ``.npz`` holds ``image``,
    ``seed`` and ``code``), analysed and meshed with its clinic station (``params``: stage
    parameters, ``{"peaks": {...}}``), and that station."""
    from rasterserver.pipeline import run_chain
    from rasterserver.simulator.body import clinic_station
    from rasterserver.stage import StageContext

    kept = np.load(KEPT / f"{name}.npz")
    station = clinic_station(int(kept["seed"]), str(kept["code"]))
    context = StageContext(calibration=station, raster=station.raster_definition)
    records = run_chain(kept["image"], params=params, context=context, until="analysis")
    mesh = run_chain(records["surface"], context=context, until="mesh")["mesh"]
    surface, shape = records["surface"], records["analysis"]
    assert isinstance(surface, Surface) and isinstance(shape, BackShape)
    assert isinstance(mesh, MeshRecord)
    return Visit(surface, mesh, shape, label=label), station
