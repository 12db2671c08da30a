"""Engines: the local cluster's worker settings, batched Dask tasks, the engine choice."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import geometry_truth as gt
import numpy as np
import pytest
from distributed.diagnostics.plugin import SchedulerPlugin

from rasterserver.archive import Archive
from rasterserver.config import Settings
from rasterserver.engines import DASK_BATCH, dask_client, engine_name
from rasterserver.jobs import process_many


def _worker_settings() -> tuple[bool, str | None]:
    import dask

    return (
        bool(dask.config.get("distributed.worker.profile.enabled")),
        os.environ.get("MALLOC_TRIM_THRESHOLD_"),
    )


@pytest.mark.slow
def test_local_workers_keep_glibcs_adaptive_malloc_and_no_profiler() -> None:
    # Dask's defaults cost a worker three times the CPU of the same work in-process here
    # (BENCHMARKS.md, "Reprocessing throughput"): the settings must reach the worker processes
    with dask_client(n_workers=1) as client:
        (settings,) = client.run(_worker_settings).values()
    assert settings == (False, None)


def _stream_log_lengths(dask_scheduler: Any) -> list[int | None]:
    return [comm.recent_message_log.maxlen for comm in dask_scheduler.stream_comms.values()]


@pytest.mark.slow
def test_the_coordinator_keeps_few_sent_messages() -> None:
    # each batched stream keeps its recent messages for debugging; with a job's tasks (eight
    # plans each) Dask's default of 1,000 held ~6 MB per 1,000 acquisitions in the
    # coordinator (BENCHMARKS.md, "Reprocessing throughput", 2026-11-27)
    with dask_client(n_workers=1) as client:
        lengths = client.run_on_scheduler(_stream_log_lengths)
        assert lengths and all(n is not None and n <= 16 for n in lengths)
        assert client.scheduler_comm.recent_message_log.maxlen <= 16


def test_a_batch_reports_each_acquisition_on_its_own(settings: Settings) -> None:
    # three acquisitions in one Dask task (a batch not full, sent when the coordinator
    # waits); the one that cannot be processed fails alone
    import distributed

    from rasterserver.archive import FrameSource

    archive, uids = gt.archive_with_frames(
        settings, {"back": gt.rendering("back").image, "black": np.zeros((604, 576), np.uint8)}
    )
    with archive:
        uncalibrated = archive.ingest(
            [FrameSource(np.zeros((604, 576), np.uint8), role="raster", name="u.npy")],
            patient="P1",
        ).uid
        order = [uids["back"], uncalibrated, uids["black"]]
        tasks: list[str] = []
        with (
            distributed.LocalCluster(
                n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
            ) as cluster,
            distributed.Client(cluster) as client,
        ):
            cluster.scheduler.add_plugin(_Tasks(tasks))
            outcomes = process_many(archive, order, client=client, max_in_flight=DASK_BATCH)
    assert [o.uid for o in outcomes] == order
    assert [o.status for o in outcomes] == ["done", "failed", "done"]
    assert "calibration" in outcomes[1].error
    assert outcomes[0].computed == 7 and outcomes[2].reason
    assert [key.split("-")[0] for key in tasks] == ["work_batch"]  # one task for the three


class _Tasks(SchedulerPlugin):
    """The keys of the tasks the (in-process) scheduler received."""

    def __init__(self, sink: list[str]) -> None:
        self.sink = sink

    def update_graph(self, scheduler: object, *, keys: set[object], **kwargs: object) -> None:
        self.sink.extend(str(key) for key in keys)


@pytest.mark.parametrize(
    ("count", "dask", "scheduler", "default", "expected"),
    [
        (1, None, None, "tcp://s:8786", "in-process"),
        (5, None, None, "tcp://s:8786", "tcp://s:8786"),
        (5, True, None, None, "local-cluster"),
        (5, False, None, "tcp://s:8786", "in-process"),
        (5, False, "tcp://x:1", None, "tcp://x:1"),
    ],
)
def test_engine_name_when_told(
    count: int, dask: bool | None, scheduler: str | None, default: str | None, expected: str
) -> None:
    assert engine_name(count, dask=dask, scheduler=scheduler, default_scheduler=default) == expected


def test_engine_name_unsaid_on_many_follows_the_measured_threshold(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from rasterserver.engines import LOCAL_CLUSTER_MIN

    assert LOCAL_CLUSTER_MIN is not None  # measured: BENCHMARKS.md "Reprocessing throughput"
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    assert engine_name(LOCAL_CLUSTER_MIN - 1) == "in-process"
    assert engine_name(LOCAL_CLUSTER_MIN) == "local-cluster"
    assert engine_name(LOCAL_CLUSTER_MIN, default_scheduler="tcp://s:8786") == "tcp://s:8786"
    monkeypatch.setattr(os, "cpu_count", lambda: 1)  # one worker on one core gains nothing
    assert engine_name(10 * LOCAL_CLUSTER_MIN) == "in-process"


def test_the_http_server_computes_in_its_process_unless_a_scheduler_is_set(
    tmp_path: Path,
) -> None:
    # a web server's threads never start a local cluster, whatever the job's size
    from rasterserver.config import sqlite_url
    from rasterserver.services.jobs import server_dask

    root = tmp_path / "archive"
    for scheduler, expected in ((None, False), ("tcp://scheduler:8786", None)):
        archive = Archive.create(
            Settings(archive=root, database_url=sqlite_url(root), dask_scheduler=scheduler)
        )
        with archive:
            assert server_dask(archive) is expected
