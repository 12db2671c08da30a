"""The README's main job runs end to end on the embedded default and on PostgreSQL."""

from __future__ import annotations

from rasterserver.archive import Archive
from rasterserver.config import Settings
from rasterserver.demo import DEMO_PATIENT, raster_like_frame, run_demo


def test_demo_ingests_lists_and_verifies(settings: Settings) -> None:
    lines: list[str] = []
    result = run_demo(settings, visits=2, log=lines.append)
    assert result.problems == 0 and result.verified_frames == 2
    assert len(result.acquisitions) == 2
    with Archive(settings) as archive:
        stored = archive.read_frame(result.acquisitions[-1].uid)
    assert (stored == raster_like_frame(0)).all()
    assert any(DEMO_PATIENT in line for line in lines)
    # Running again adds visits instead of failing on the existing patient.
    assert len(run_demo(settings, visits=1, log=lines.append).acquisitions) == 3
