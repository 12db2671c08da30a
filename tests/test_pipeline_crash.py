"""Kill a real processing process mid-run: its run does not stay "running", and the acquisition
can be processed again. Runs of live processes and of other hosts are left alone.

On SQLite and PostgreSQL (the ``settings`` fixture).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterator

import geometry_truth as gt
import pytest
from sqlalchemy import select

from rasterserver.archive import Archive
from rasterserver.catalog.models import PipelineRun
from rasterserver.config import Settings
from rasterserver.pipeline import INTERRUPTED, Pipeline
from rasterserver.runner import current_runner, local_host

UNTIL = "lines"  # two stages: enough to be killed between them, quick to finish afterwards

SCRIPT = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from rasterserver.archive import Archive
    from rasterserver.config import Settings
    from rasterserver.pipeline import Pipeline
    from rasterserver.store.derived import DerivedStore

    archive_dir, url, uid, step, until = sys.argv[1:6]

    def stop(run_id):
        print(run_id, flush=True)  # the test kills us now, with SIGKILL
        time.sleep(300)

    pipeline = Pipeline(Archive(Settings(archive=Path(archive_dir), database_url=url)))
    if step == "computing":  # the run row is committed, nothing is written yet
        pipeline.compute = lambda plan: stop(plan.run_id)
    else:  # "written": one result file written, its row not yet committed
        write = DerivedStore.write

        def write_then_stop(self, *args, **kwargs):
            result = write(self, *args, **kwargs)
            stop(run_ids[-1])
            return result

        DerivedStore.write = write_then_stop
        plan = pipeline.plan
        run_ids = []

        def plan_and_note(*args, **kwargs):
            planned = plan(*args, **kwargs)
            run_ids.append(planned.run_id)
            return planned

        pipeline.plan = plan_and_note
    pipeline.process(uid, until=until)
    print("finished without being killed", flush=True)
    """
)


@pytest.fixture
def archived(settings: Settings) -> Iterator[tuple[Archive, str]]:
    archive, uids = gt.archive_with_frames(settings, {"back": gt.rendering("back").image})
    yield archive, uids["back"]
    archive.close()


def _stored(archive: Archive, run_id: int) -> PipelineRun:
    with archive.session() as s:
        row = s.scalar(select(PipelineRun).where(PipelineRun.id == run_id))
    assert row is not None
    return row


def _add_run(archive: Archive, uid: str, *, host: str, runner: str) -> int:
    acquisition = archive.acquisition(uid)
    with archive.session() as s:
        run = PipelineRun(acquisition_id=acquisition.id, chain=[], status="running",
                          host=host, runner=runner)
        s.add(run)
    return run.id


@pytest.mark.parametrize(
    ("step", "noticed_by"), [("computing", "listing"), ("written", "reprocessing")]
)
def test_a_killed_process_leaves_an_interrupted_run_and_processing_again_finishes(
    archived: tuple[Archive, str], settings: Settings, step: str, noticed_by: str
) -> None:
    archive, uid = archived
    pipeline = Pipeline(archive)
    child = subprocess.Popen(
        [sys.executable, "-c", SCRIPT, str(settings.archive), settings.database_url, uid,
         step, UNTIL],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        line = child.stdout.readline()  # type: ignore[union-attr]
        assert line.strip().isdigit(), child.stderr.read()  # type: ignore[union-attr]
        run_id = int(line)
        # its process is alive: the run is running, and nothing marks it otherwise
        assert [r.status for r in pipeline.runs(uid)] == ["running"]
        report = pipeline.reap()
        assert (report.marked, report.alive) == (0, 1)
        assert _stored(archive, run_id).runner.startswith(f"{local_host()}:{child.pid}@")
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=30)
        child.stdout.close()  # type: ignore[union-attr]
        child.stderr.close()  # type: ignore[union-attr]
    assert child.returncode == -signal.SIGKILL
    assert _stored(archive, run_id).status == "running"  # nothing ran to notice yet

    if noticed_by == "listing":
        (run,) = pipeline.runs(uid)
        assert run.id == run_id and run.status == "failed"
        result = pipeline.process(uid, until=UNTIL)
        assert (result.computed, result.reused) == (2, 0)
    else:
        result = pipeline.process(uid, until=UNTIL)
        # the first result file, written before the kill, is adopted: verify finds no orphan
        assert not pipeline.verify().problems
    stored = _stored(archive, run_id)
    assert stored.status == "failed" and stored.finished_at is not None
    assert stored.error == (
        f"{INTERRUPTED}the process running it ({local_host()}:{child.pid}) is gone"
    )
    runs = pipeline.runs(uid)
    assert [(r.id, r.status) for r in runs] == [(run_id, "failed"), (result.run_id, "done")]
    assert pipeline.reap().marked == 0
    assert pipeline.unprocessed() == []


def test_runs_of_other_hosts_and_live_processes_are_left_alone(
    archived: tuple[Archive, str],
) -> None:
    archive, uid = archived
    pipeline = Pipeline(archive)
    here = local_host()
    elsewhere = _add_run(archive, uid, host="elsewhere.invalid",
                         runner="elsewhere.invalid:4242@boot/1")
    legacy = _add_run(archive, uid, host=here, runner="")  # before revision 0008
    alive = _add_run(archive, uid, host=here, runner=current_runner())
    # listing, selecting and processing check what they can, and leave the rest
    assert pipeline.unprocessed() == [uid]
    assert pipeline.process(uid, until="peaks").computed == 1
    assert [r.status for r in pipeline.runs(uid)] == ["running", "running", "running", "done"]
    report = pipeline.reap()
    assert (report.marked, report.alive) == (0, 1)
    assert report.unchecked == {"elsewhere.invalid": 1, here: 1}
    # until staff say the other host has stopped; naming this host never touches a live run
    report = pipeline.reap(hosts=["elsewhere.invalid", here], dry_run=True)
    assert report.marked == 2 and _stored(archive, elsewhere).status == "running"
    assert pipeline.reap(hosts=["elsewhere.invalid", here]).marked == 2
    assert _stored(archive, elsewhere).error.startswith(
        f"{INTERRUPTED}host elsewhere.invalid was reported to run it no longer")
    assert _stored(archive, legacy).status == "failed"
    assert _stored(archive, alive).status == "running"


def test_a_pid_reused_by_another_process_does_not_keep_a_run_running(
    archived: tuple[Archive, str],
) -> None:
    if not os.path.exists("/proc/self/stat"):
        pytest.skip("process start times come from /proc")
    archive, uid = archived
    own, _, token = current_runner().partition("@")
    boot, start, namespace = token.split("/")
    # the recorded process had this process's pid, but started at another time
    reused = _add_run(archive, uid, host=local_host(),
                      runner=f"{own}@{boot}/{int(start) - 1}/{namespace}")
    (run,) = Pipeline(archive).runs(uid)
    assert run.id == reused and run.status == "failed"
    assert run.error.startswith(INTERRUPTED) and own in run.error
