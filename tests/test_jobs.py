"""Jobs over many acquisitions: in process and on Dask, failures recorded, reuse, progress."""

from __future__ import annotations

import geometry_truth as gt
import numpy as np
import pytest
from sqlalchemy import func, select

from rasterserver.catalog.models import PipelineRun, StageResult
from rasterserver.config import Settings
from rasterserver.jobs import JobOutcome, process_many


@pytest.fixture
def three(settings: Settings):
    frames = {"back": gt.rendering("back").image, "black": np.zeros((604, 576), np.uint8)}
    archive, uids = gt.archive_with_frames(settings, frames)
    # taken without a station, so no calibration applies: its processing must fail, recorded
    # (a frame of the wrong size is refused at ingest now, so it cannot serve here)
    from rasterserver.archive import FrameSource

    uids["uncalibrated"] = archive.ingest(
        [FrameSource(np.zeros((604, 576), np.uint8), role="raster", name="u.npy")],
        patient="P1",
    ).uid
    yield archive, uids
    archive.close()


def _rows(archive, model) -> int:
    with archive.session() as s:
        return int(s.scalar(select(func.count()).select_from(model)))


def _check(outcomes: list[JobOutcome], uids: dict[str, str]) -> None:
    assert [o.uid for o in outcomes] == list(uids.values())
    back, black, uncalibrated = outcomes
    assert back.status == "done" and back.computed == 7 and back.error == ""
    assert black.status == "done" and black.reason  # empty result, with the reason
    assert uncalibrated.status == "failed" and "calibration" in uncalibrated.error


def test_in_process_with_progress_and_failures(three) -> None:
    archive, uids = three
    calls: list[tuple[int, int]] = []
    outcomes = process_many(
        archive, list(uids.values()), progress=lambda d, t: calls.append((d, t))
    )
    _check(outcomes, uids)
    assert calls == [(0, 3), (1, 3), (2, 3), (3, 3)]
    assert _rows(archive, StageResult) == 14
    again = process_many(archive, list(uids.values())[:2])
    assert [(o.computed, o.reused) for o in again] == [(0, 7), (0, 7)]
    assert _rows(archive, StageResult) == 14


def test_on_a_dask_client(three) -> None:
    distributed = pytest.importorskip("distributed")
    archive, uids = three
    calls: list[tuple[int, int]] = []
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        outcomes = process_many(
            archive,
            list(uids.values()),
            client=client,
            max_in_flight=1,
            progress=lambda d, t: calls.append((d, t)),
        )
        _check(outcomes, uids)
        assert calls[0] == (0, 3) and calls[-1] == (3, 3) and len(calls) == 4
        # a second job finds everything stored and submits nothing
        again = process_many(archive, [uids["back"]], client=client)
        assert again[0].status == "done" and again[0].computed == 0
    with archive.session() as s:
        statuses = sorted(s.scalars(select(PipelineRun.status)))
    assert statuses == ["done", "done", "done", "failed"]
    assert _rows(archive, StageResult) == 14


@pytest.mark.slow
def test_on_a_local_cluster_of_processes(settings: Settings) -> None:
    pytest.importorskip("distributed")
    archive, uids = gt.archive_with_frames(settings, {"back": gt.rendering("back").image})
    with archive:
        outcomes = process_many(archive, list(uids.values()), dask=True, n_workers=1)
        assert outcomes[0].status == "done" and outcomes[0].computed == 7
        with archive.session() as s:
            hosts = set(s.scalars(select(StageResult.host)))
        assert len(hosts) == 1 and hosts != {""}


@pytest.mark.parametrize("on_dask", [False, True], ids=["in-process", "dask"])
def test_several_targets_share_their_stages(three, on_dask: bool) -> None:
    # `process` computes the mesh and the analysis: one surface, counted once
    archive, uids = three
    targets = ("mesh", "analysis")
    wanted = [uids["back"], uids["uncalibrated"]]
    if not on_dask:
        outcomes = process_many(archive, wanted, until=targets)
    else:
        distributed = pytest.importorskip("distributed")
        with (
            distributed.LocalCluster(
                n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
            ) as cluster,
            distributed.Client(cluster) as client,
        ):
            outcomes = process_many(archive, wanted, until=targets, client=client)
    back, uncalibrated = outcomes
    assert back.status == "done" and (back.computed, back.reused) == (8, 0)
    assert uncalibrated.status == "failed" and "calibration" in uncalibrated.error
    assert _rows(archive, StageResult) == 8
    again = process_many(archive, [uids["back"]], until=targets)
    assert (again[0].computed, again[0].reused) == (0, 8)
