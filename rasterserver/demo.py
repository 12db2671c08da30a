"""The main job on the embedded default: make a demo patient's data, archive it, check it.

``rasterserver demo`` runs this on SQLite and a local archive folder, so a newcomer sees the
whole path (ingest → catalogue → verify) on a fresh machine with one command.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rasterserver.archive import Archive, FrameSource
from rasterserver.catalog.models import Acquisition
from rasterserver.config import Settings
from rasterserver.errors import NotFoundError

DEMO_PATIENT = "DEMO-0001"
DEMO_STATION = "demo-station"


@dataclass
class DemoResult:
    """What the demo did."""

    acquisitions: list[Acquisition]
    verified_frames: int
    problems: int


def raster_like_frame(seed: int, *, shape: tuple[int, int] = (604, 576)) -> np.ndarray:
    """Return a quick stand-in camera frame: bright horizontal lines, 1 per 10 rows, on noise.

    Parameters
    ----------
    seed : int
        Seed of the noise and of the lines' gentle waviness.
    shape : tuple of int
        ``(rows, columns)``.

    Returns
    -------
    numpy.ndarray
        ``uint8`` frame.
    """
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    bend = 6.0 * np.sin(cols / shape[1] * np.pi) * (1 + 0.2 * rng.standard_normal())
    phase = (rows - bend) % 10.0
    lines = np.exp(-0.5 * ((phase - 5.0) / 1.1) ** 2)
    image = 20 + 180 * lines + rng.normal(0, 2.0, shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def run_demo(
    settings: Settings, *, visits: int = 3, log: Callable[[str], None] = print
) -> DemoResult:
    """Create the archive if needed, ingest a demo patient's visits, list and verify them.

    Parameters
    ----------
    settings : Settings
        Where the archive and catalogue are (SQLite inside the archive by default).
    visits : int
        How many visits (one acquisition each) to ingest.
    log : callable
        Where progress lines go.

    Returns
    -------
    DemoResult
    """
    archive = Archive.create(settings)
    try:
        try:
            archive.patient(DEMO_PATIENT)
        except NotFoundError:
            archive.add_patient(DEMO_PATIENT, name="Demo Patient", sex="female")
        first = dt.datetime(2024, 1, 15, 9, 0, tzinfo=dt.UTC)
        for visit in range(visits):
            when = first + dt.timedelta(days=182 * visit)
            acq = archive.ingest(
                [FrameSource(raster_like_frame(visit), role="raster", name=f"visit{visit}")],
                patient=DEMO_PATIENT,
                acquired_at=when,
                operator="demo",
            )
            log(f"ingested visit {visit + 1}/{visits}: acquisition {acq.uid}")
        acquisitions = archive.acquisitions(patient=DEMO_PATIENT)
        log(f"{DEMO_PATIENT} has {len(acquisitions)} acquisition(s) in the archive")
        report = archive.verify()
        log(
            f"verify: {report.acquisitions_checked} acquisitions, {report.frames_checked} "
            f"frames, {len(report.problems)} problem(s)"
        )
        return DemoResult(acquisitions, report.frames_checked, len(report.problems))
    finally:
        archive.close()
