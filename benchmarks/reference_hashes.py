"""Content hashes of every stage's record on 17 reference frames: "same bits" for a refactor.

A change that is meant not to alter any result (a loop compiled with numba, a lookup done
once instead of twice) keeps every plugin's version, so the archive's stored results stay
valid; this script is how such a change is checked. It runs the whole chain (image → mesh)
on the medium back of the tests' station and on 16 clinic scenes of
``benchmarks/real_bodies.py`` (seeds 30000-30015: head, arms, clothing, four rasters) and
prints one line per frame and stage with the record's content hash.

Usage::

    python benchmarks/reference_hashes.py > before.txt     # on the old code
    python benchmarks/reference_hashes.py | diff before.txt -
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

import geometry_truth as gt  # noqa: E402

from rasterserver.chain import run_chain  # noqa: E402
from rasterserver.simulator.back import make_back, preset  # noqa: E402
from rasterserver.simulator.body import clinic_station, make_body, random_body  # noqa: E402
from rasterserver.simulator.render import RenderSettings, render  # noqa: E402
from rasterserver.stage import StageContext  # noqa: E402

CODES = ("default", "mseq7", "w8-1to2", "w9-45to55")
CLINIC_SEEDS = range(30000, 30016)


def _print_chain(name: str, image: object, context: StageContext) -> None:
    for kind, record in run_chain(image, context=context).items():  # type: ignore[arg-type]
        print(f"{name} {kind} {record.content_hash()}", flush=True)


def main() -> None:
    """Print ``frame stage hash`` lines for the 17 reference frames."""
    station = gt.station()
    image = render(make_back(preset("moderate")), station, settings=RenderSettings(), seed=1).image
    _print_chain("back-moderate", image, StageContext(station, station.raster_definition))
    for seed in CLINIC_SEEDS:
        code = CODES[seed % len(CODES)]
        station = clinic_station(seed, code)
        settings = RenderSettings(threads=1)
        image = render(make_body(random_body(seed)), station, settings=settings, seed=seed).image
        _print_chain(f"clinic-{seed}", image, StageContext(station, station.raster_definition))


if __name__ == "__main__":
    main()
