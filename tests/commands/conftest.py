"""Fixtures shared by the command tests."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from rasterserver.archive import Archive
from rasterserver.cli import main
from rasterserver.config import Settings


@pytest.fixture
def cli(settings: Settings) -> Callable[..., int]:
    """Run the CLI on the test archive (catalogue migrated); returns the exit code."""
    base = ["--archive", str(settings.archive), "--database-url", settings.database_url]

    def run(*args: str) -> int:
        return main([*base, *args])

    assert run("db", "upgrade") == 0
    return run


@pytest.fixture
def processed(settings: Settings) -> str:
    """The uid of a simulated acquisition stored and processed through every stage."""
    from rasterserver.demo import simulate_visits
    from rasterserver.optics import default_station
    from rasterserver.pipeline import Pipeline
    from rasterserver.simulated_visits import archive_visits

    with Archive(settings) as archive:
        (acq,) = archive_visits(
            archive, simulate_visits(1, supersample=1), station=default_station(),
            patient="P9",
        )
        Pipeline(archive).process(acq.uid)
    return acq.uid
