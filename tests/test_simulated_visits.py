"""Simulated patients stored in the archive: progression and idempotent registration."""

from __future__ import annotations

import numpy as np

from rasterserver.archive import Archive
from rasterserver.config import Settings
from rasterserver.optics import default_station
from rasterserver.simulated_visits import (
    FIRST_VISIT,
    VISIT_INTERVAL,
    SimulatedVisit,
    archive_visits,
    progressed,
)
from rasterserver.simulator.back import preset


def test_progression_grows_every_curve_and_keeps_a_straight_spine() -> None:
    moderate = preset("moderate")
    later = progressed(moderate, 2, 0.5)
    for before, after in zip(moderate.curves, later.curves, strict=True):
        assert np.isclose(after.lateral_deviation, before.lateral_deviation * 2.25)
        assert abs(after.rotation) <= 60
    assert progressed(preset("normal"), 3, 0.5) == preset("normal")
    assert progressed(moderate, 0, 0.5) == moderate


def test_visits_archived_six_months_apart_station_registered_once(settings: Settings) -> None:
    station = default_station()
    image = np.zeros((604, 576), np.uint8)
    visits = [SimulatedVisit(preset("moderate"), image) for _ in range(2)]
    with Archive.create(settings) as archive:
        first = archive_visits(archive, visits, station=station, patient="SIM-1")
        again = archive_visits(archive, visits[:1], station=station, patient="SIM-1")
        assert [a.acquired_at for a in first] == [FIRST_VISIT, FIRST_VISIT + VISIT_INTERVAL]
        assert len(archive.calibrations("simulator")) == 1  # identical: stored once
        assert again[0].calibration_id == first[0].calibration_id
        assert len(archive.acquisitions(patient="SIM-1")) == 3
        cal = archive.calibration("simulator")
        assert cal.parameters == station.to_dict()
