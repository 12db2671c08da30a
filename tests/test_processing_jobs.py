"""Processing jobs in the catalogue: selection, pause, cancel, resume, and a real Dask cluster
(a ``dask scheduler`` and two ``dask worker`` processes on loopback) with a worker killed
mid-job. On SQLite and PostgreSQL."""

from __future__ import annotations

import datetime as dt
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import geometry_truth as gt
import numpy as np
import pytest
from sqlalchemy import func, select

from rasterserver.archive import Archive
from rasterserver.catalog.job_models import ProcessingJob, ProcessingTask
from rasterserver.catalog.models import Acquisition, StageResult
from rasterserver.config import Settings
from rasterserver.errors import ConflictError, InputError, NotFoundError
from rasterserver.pipeline import Pipeline
from rasterserver.processing_jobs import (
    Selection,
    cancel_job,
    create_job,
    find_job,
    job_status,
    pause_job,
    resolve_selection,
    run_job,
)

#: Stages of the chain up to the mesh: results per acquisition of a job with target mesh.
MESH_STAGES = 7


def many(settings: Settings, count: int, *, black: int = 0) -> tuple[Archive, list[str]]:
    """An archive with ``count`` acquisitions of the simulated back (and ``black`` black
    frames, which process fast to empty results), oldest first."""
    image = gt.rendering("back").image
    frames = {f"back{i}": image for i in range(count)}
    frames |= {f"black{i}": np.zeros_like(image) for i in range(black)}
    archive, uids = gt.archive_with_frames(settings, frames)
    return archive, list(uids.values())


def results_per_acquisition(archive: Archive) -> dict[str, tuple[int, int]]:
    """Per acquisition uid: (stage_result rows, distinct chain keys)."""
    with archive.session() as s:
        rows = s.execute(
            select(Acquisition.uid, func.count(StageResult.id),
                   func.count(func.distinct(StageResult.chain_key)))
            .join(StageResult, StageResult.acquisition_id == Acquisition.id)
            .group_by(Acquisition.uid)
        ).all()
    return {uid: (n, keys) for uid, n, keys in rows}


def assert_each_result_once(archive: Archive, uids: list[str], stages: int) -> None:
    """Every acquisition has its chain's results exactly once, and every file its row."""
    counts = results_per_acquisition(archive)
    assert counts == {uid: (stages, stages) for uid in uids}
    problems = Pipeline(archive).verify().problems
    # a file written just before a kill and adopted by the redo is not a problem; a partial
    # write of a killed process is reported as temporary (safe to delete), never a row
    assert {p.kind for p in problems} <= {"temporary"}, problems


def wait_until(condition, timeout: float = 120.0, step: float = 0.05) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(step)


def job_row(archive: Archive, job_id: str) -> ProcessingJob:
    return find_job(archive, job_id)


# --- selection and creation ----------------------------------------------------------------------


def test_selection_resolves_to_tasks_stored_with_the_job(settings: Settings) -> None:
    archive, uids = many(settings, 3, black=1)
    with archive:
        # all: oldest first; named uids first; an unknown uid is kept (its task fails)
        everything = [u for u, _ in resolve_selection(archive, Selection(all=True))]
        assert everything == uids
        named = resolve_selection(archive, Selection(uids=(uids[2], "f" * 32), all=True))
        assert [u for u, _ in named] == [uids[2], "f" * 32, uids[0], uids[1], uids[3]]
        assert named[1][1] is None
        # date range: the frames were taken at 10:00, 10:01, ... UTC
        base = dt.datetime(2025, 3, 1, 10, 0, tzinfo=dt.UTC)
        window = Selection(since=base + dt.timedelta(minutes=1),
                           before=base + dt.timedelta(minutes=3))
        assert [u for u, _ in resolve_selection(archive, window)] == uids[1:3]
        assert [u for u, _ in resolve_selection(archive, Selection(station="clinic-1"))] == uids
        assert [u for u, _ in resolve_selection(archive, Selection(patient="P1"))] == uids
        with pytest.raises(NotFoundError):
            resolve_selection(archive, Selection(station="nowhere"))
        with pytest.raises(InputError):
            resolve_selection(archive, Selection(since=base, before=base))
        # results from a given plugin version: none yet, then the processed one
        by_plugin = Selection(plugin="peaks.first-moment",
                              plugin_version=Pipeline(archive).registry.get(
                                  "peaks.first-moment").version)
        assert resolve_selection(archive, by_plugin) == []
        Pipeline(archive).process(uids[1], until="peaks")
        assert [u for u, _ in resolve_selection(archive, by_plugin)] == [uids[1]]
        assert resolve_selection(archive, Selection(plugin="peaks.first-moment",
                                                    plugin_version="0-no-such")) == []
        unprocessed = [u for u, _ in resolve_selection(archive, Selection(unprocessed=True))]
        assert unprocessed == [uids[0], uids[2], uids[3]]

        job, count = create_job(archive, Selection(all=True), targets=["mesh"], owner="dr x")
        assert count == 4
        row = job_row(archive, job.id)
        assert row.state == "queued" and row.total == 4 and row.owner == "dr x"
        assert row.selection == {"all": True} and row.targets == ["mesh"]
        steps = row.chain["resolved"]["mesh"]
        assert [s["stage"] for s in steps][-1] == "mesh" and all(s["version"] for s in steps)
        with archive.session() as s:
            tasks = list(s.scalars(select(ProcessingTask).where(ProcessingTask.job_id == job.id)
                                   .order_by(ProcessingTask.position)))
        assert [t.uid for t in tasks] == uids and {t.state for t in tasks} == {"pending"}
        # nothing selected: nothing stored
        empty, none = create_job(archive, Selection(patient="P1", before=base))
        assert none == 0
        with archive.session() as s:
            assert s.get(ProcessingJob, empty.id) is None
        # a misspelt plugin is refused before anything is stored
        with pytest.raises(NotFoundError):
            create_job(archive, Selection(all=True), chain={"peaks": "no-such"})


# --- running, pausing, cancelling, resuming ------------------------------------------------------


def _run_in_thread(archive: Archive, job_id: str, **kwargs) -> tuple[threading.Thread, dict]:
    out: dict = {}

    def target() -> None:
        try:
            out["status"] = run_job(archive, job_id, **kwargs)
        except BaseException as exc:  # handed to the test
            out["error"] = exc

    thread = threading.Thread(target=target)
    thread.start()
    return thread, out


def test_run_pause_resume_and_progress(settings: Settings, monkeypatch) -> None:
    archive, uids = many(settings, 8)
    # one acquisition per batch and the job's state asked after each: the pause, requested
    # once two are done, is seen before the last (however fast the chain and the files)
    monkeypatch.setattr("rasterserver.engines.IN_PROCESS_BATCH", 1)
    monkeypatch.setattr("rasterserver.jobs.COMMIT_EVERY_S", 0.0)
    monkeypatch.setattr("rasterserver.processing_jobs._POLL_S", 0.0)
    with archive:
        job, _ = create_job(archive, Selection(all=True), targets=["mesh"])
        seen: list[tuple[int, int]] = []
        pauses: list[str] = []

        def progress(st) -> None:
            seen.append((st.job.done + st.job.failed, st.job.total))
            if st.job.done >= 2 and not pauses:
                pauses.append(pause_job(archive, job.id).state)

        thread, out = _run_in_thread(archive, job.id, dask=False, progress=progress)
        thread.join(120)
        assert pauses == ["paused"]
        assert "error" not in out, out.get("error")
        status = out["status"]
        assert status.job.state == "paused" and 2 <= status.job.done < 8
        assert status.left == 8 - status.job.done and status.job.finished_at is None
        assert seen[0] == (0, 8) and seen == sorted(seen)
        with pytest.raises(ConflictError, match="paused"):
            pause_job(archive, job.id)
        done_before = status.job.done
        final = run_job(archive, job.id, dask=False)
        assert final.job.state == "done" and final.job.done == 8 and final.left == 0
        assert final.job.finished_at is not None and final.rate and final.rate > 0
        assert_each_result_once(archive, uids, MESH_STAGES)
        with archive.session() as s:
            attempts = list(s.scalars(select(ProcessingTask.attempts)
                                      .where(ProcessingTask.job_id == job.id)))
        # tasks done before the pause are not started again
        assert attempts.count(1) == 8 and done_before < 8
        with pytest.raises(ConflictError, match="finished"):
            run_job(archive, job.id)
        with pytest.raises(ConflictError):
            cancel_job(archive, job.id)


def test_cancel_stops_and_cannot_be_resumed(settings: Settings, monkeypatch) -> None:
    archive, _uids = many(settings, 8)
    # as in the pause test: the cancel, requested once one is done, is seen before the last
    monkeypatch.setattr("rasterserver.engines.IN_PROCESS_BATCH", 1)
    monkeypatch.setattr("rasterserver.jobs.COMMIT_EVERY_S", 0.0)
    monkeypatch.setattr("rasterserver.processing_jobs._POLL_S", 0.0)
    with archive:
        job, _ = create_job(archive, Selection(all=True), targets=["mesh"])
        cancels: list[str] = []

        def progress(st) -> None:
            if st.job.done >= 1 and not cancels:
                cancels.append(cancel_job(archive, job.id).state)

        thread, out = _run_in_thread(archive, job.id, dask=False, progress=progress)
        thread.join(120)
        assert cancels == ["cancelled"]
        status = out["status"]
        assert status.job.state == "cancelled" and status.job.done < 8
        assert status.job.finished_at is not None
        with pytest.raises(ConflictError, match="cancelled"):
            run_job(archive, job.id)
        with pytest.raises(ConflictError, match="cancelled"):
            cancel_job(archive, job.id)
        # what it stored is whole: every processed acquisition has its results once
        counts = results_per_acquisition(archive)
        assert set(counts.values()) <= {(MESH_STAGES, MESH_STAGES)}
        assert len(counts) >= status.job.done
        assert {p.kind for p in Pipeline(archive).verify().problems} <= {"temporary"}


def test_failures_are_counted_and_a_running_job_is_not_taken_twice(settings: Settings) -> None:
    archive, uids = many(settings, 1)
    with archive:
        job, _ = create_job(archive, Selection(uids=(uids[0], "f" * 32)), targets=["mesh"])
        # created by this (live) process: another coordinator may not take it while running
        with archive.session() as s:
            s.get(ProcessingJob, job.id).state = "running"
        status = run_job(archive, job.id, dask=False)  # the same process: allowed
        assert status.job.state == "failed" and (status.job.done, status.job.failed) == (1, 1)
        assert status.failures[0]["uid"] == "f" * 32 and status.failures[0]["exit_code"] == 3
        other, _ = create_job(archive, Selection(uids=(uids[0],)), targets=["mesh"])
        with archive.session() as s:
            row = s.get(ProcessingJob, other.id)
            row.state, row.runner = "running", f"elsewhere.example:{os.getpid()}"
        with pytest.raises(ConflictError, match="--force"):
            run_job(archive, other.id)
        forced = run_job(archive, other.id, force=True)
        assert forced.job.state == "done" and forced.job.done == 1
        with pytest.raises(NotFoundError):
            find_job(archive, "0123456789")
        assert find_job(archive, other.id[:8]).id == other.id
        assert job_status(archive, find_job(archive, other.id)).state == "done"


def test_a_job_started_over_http_is_a_catalogue_job(settings: Settings, capsys) -> None:
    from rasterserver.cli import main
    from rasterserver.services.jobs import JobRunner

    archive, uids = many(settings, 2)
    runner = JobRunner(archive)
    try:
        started = runner.submit(uids, owner="clinician-a", until="mesh")
        wait_until(lambda: runner.get(started.job.id).job.state not in ("queued", "running"))
        assert runner.get(started.job.id).job.state == "done"
    finally:
        runner.close()
        archive.close()
    base = ["--archive", str(settings.archive), "--database-url", settings.database_url]
    assert main([*base, "jobs", "show", started.job.id, "--json"]) == 0
    import json

    shown = json.loads(capsys.readouterr().out)
    assert shown["origin"] == "http" and shown["owner"] == "clinician-a"
    assert (shown["state"], shown["done"], shown["left"]) == ("done", 2, 0)


# --- a real Dask cluster -----------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class Cluster:
    """A ``dask scheduler`` and worker processes (no nanny: a killed worker stays dead)."""

    def __init__(self, tmp: Path, workers: int = 2) -> None:
        dask = str(Path(sys.executable).with_name("dask"))
        port = _free_port()
        self.address = f"tcp://127.0.0.1:{port}"
        self.logs = tmp
        env = {**os.environ, "DASK_LOGGING__DISTRIBUTED": "warning"}
        self.scheduler = self._start(
            [dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
             "--no-dashboard"], "scheduler", env)
        self.workers = [
            self._start([dask, "worker", self.address, "--nthreads", "1", "--no-nanny",
                         "--no-dashboard", "--host", "127.0.0.1"], f"worker{i}", env)
            for i in range(workers)
        ]
        from distributed import Client

        with Client(self.address, timeout=60) as client:
            client.wait_for_workers(workers, timeout=120)

    def _start(self, args: list[str], name: str, env: dict) -> subprocess.Popen:
        log = open(self.logs / f"{name}.log", "wb")  # noqa: SIM115 - closed with the process
        return subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, env=env)

    def stop(self) -> None:
        for process in [*self.workers, self.scheduler]:
            if process.poll() is None:
                process.terminate()
        for process in [*self.workers, self.scheduler]:
            try:
                process.wait(5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(20)


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    pytest.importorskip("distributed")
    logs = tmp_path / "dask-logs"
    logs.mkdir()
    running = Cluster(logs)
    try:
        yield running
    finally:
        running.stop()


@pytest.mark.slow
def test_a_job_on_a_real_cluster_survives_a_killed_worker(
    settings: Settings, cluster: Cluster
) -> None:
    archive, uids = many(settings, 24)
    with archive:
        job, _ = create_job(archive, Selection(all=True), targets=["mesh"])
        thread, out = _run_in_thread(archive, job.id, scheduler=cluster.address)
        wait_until(lambda: job_row(archive, job.id).done >= 4)
        victim = cluster.workers[0]
        os.kill(victim.pid, signal.SIGKILL)
        victim.wait(20)
        thread.join(300)
        assert not thread.is_alive()
        assert "error" not in out, out.get("error")
        status = out["status"]
        assert status.job.state == "done", status.to_dict()
        assert (status.job.done, status.job.failed, status.left) == (24, 0, 0)
        assert status.job.engine == cluster.address
        assert_each_result_once(archive, uids, MESH_STAGES)


@pytest.mark.slow
def test_a_job_on_a_real_cluster_completes_with_both_workers(
    settings: Settings, cluster: Cluster
) -> None:
    archive, uids = many(settings, 24)
    with archive:
        job, _ = create_job(archive, Selection(all=True))  # mesh and analysis
        status = run_job(archive, job.id, scheduler=cluster.address)
        assert status.job.state == "done" and status.job.done == 24, status.to_dict()
        # mesh and analysis share the surface: eight results each
        assert_each_result_once(archive, uids, MESH_STAGES + 1)
        from distributed import Client

        with Client(cluster.address) as client:
            # both workers computed (each ran some of the chains' stages)
            ran = client.run(lambda dask_worker: dask_worker.state.executed_count)
        assert len(ran) == 2 and all(count > 0 for count in ran.values())
