"""``rasterserver jobs`` and jobs made by ``process``, through the installed command: the
coordinator killed by SIGKILL mid-job and resumed, exit codes for unknown jobs and bad states.
On SQLite and PostgreSQL."""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

import pytest
import test_processing_jobs as tpj
from installed_cli import TRACEBACK, describe, installed_command, run_installed
from sqlalchemy import select

from rasterserver.archive import Archive
from rasterserver.catalog.job_models import ProcessingJob, ProcessingTask
from rasterserver.config import Settings


def _cli(settings: Settings, *args: str, **kwargs) -> subprocess.CompletedProcess[str]:
    return run_installed(*args, archive=settings.archive, database_url=settings.database_url,
                         **kwargs)


def test_coordinator_killed_mid_job_then_resumed(settings: Settings) -> None:
    archive, uids = tpj.many(settings, 24)
    archive.close()
    clean = {k: v for k, v in os.environ.items() if not k.startswith("RASTERSERVER_")}
    with open(settings.archive.parent / "process.err", "w+b") as err:
        process = subprocess.Popen(
            [installed_command(), "--archive", str(settings.archive), "--database-url",
             settings.database_url, "process", "--all", "--until", "mesh", "--no-dask"],
            stdout=subprocess.DEVNULL, stderr=err, env=clean,
        )
        try:
            with Archive(settings) as watch:
                def started() -> list[ProcessingJob]:
                    with watch.session() as s:
                        return list(s.scalars(select(ProcessingJob)))

                tpj.wait_until(lambda: started() and started()[0].done >= 4, timeout=300)
                process.send_signal(signal.SIGKILL)
                assert process.wait(30) == -signal.SIGKILL
        finally:
            if process.poll() is None:
                process.kill()
                process.wait(30)
        err.seek(0)
        first = err.read().decode().splitlines()[0]
    (job,) = started()
    assert first.startswith(f"job {job.id}: 24 acquisition(s)")
    assert job.done < 24, "the job ended before the kill: make it longer"

    shown = _cli(settings, "jobs", "show", job.id, "--json")
    assert shown.returncode == 0, describe(shown)
    status = json.loads(shown.stdout)
    assert status["state"] == "interrupted" and status["left"] == 24 - status["done"]
    listed = _cli(settings, "jobs", "list")
    assert f"{job.id}\tinterrupted\t" in listed.stdout, describe(listed)

    resumed = _cli(settings, "jobs", "resume", job.id[:10])
    assert resumed.returncode == 0, describe(resumed)
    assert f"job {job.id} done: 24 done, 0 failed, 0 left of 24" in resumed.stdout
    assert TRACEBACK not in resumed.stderr
    with Archive(settings) as archive:
        tpj.assert_each_result_once(archive, uids, tpj.MESH_STAGES)
        with archive.session() as s:
            attempts = list(s.scalars(select(ProcessingTask.attempts)
                                      .where(ProcessingTask.job_id == job.id)))
        # tasks finished before the kill were not started again; the one in flight was
        assert sorted(attempts)[:job.done] == [1] * job.done and max(attempts) <= 2
    again = _cli(settings, "jobs", "resume", job.id)
    assert again.returncode == 4 and "nothing left" in again.stderr, describe(again)


def test_exit_codes_and_messages(settings: Settings, capsys) -> None:
    # in this process (the installed command is exercised above): the same main()
    from rasterserver.cli import main

    archive, uids = tpj.many(settings, 2)
    archive.close()
    base = ["--archive", str(settings.archive), "--database-url", settings.database_url]

    def cli(*args: str) -> tuple[int, str, str]:
        code = main([*base, *args])
        out = capsys.readouterr()
        return code, out.out, out.err

    code, _out, err = cli("jobs", "show", "0" * 32)
    assert code == 3 and "unknown job" in err
    for action in ("pause", "resume", "cancel"):
        code, _out, err = cli("jobs", action, "abcdef")
        assert code == 3 and "unknown job" in err
    code, _out, err = cli("jobs", "list", "--state", "sleeping")
    assert code == 2 and "unknown job state" in err

    code, out, err = cli("process", uids[0], "--until", "peaks", "--json")
    assert code == 0 and json.loads(out)["status"] == "done"
    job_id = err.split()[1].rstrip(":")
    assert len(job_id) == 32
    for action, needle in (("pause", "only a queued or running job"),
                           ("cancel", "is done"), ("resume", "nothing left")):
        code, _out, err = cli("jobs", action, job_id)
        assert code == 4 and needle in err, (action, err)
    code, out, _err = cli("jobs", "show", job_id)
    assert code == 0 and "state      done" in out
    assert "peaks.first-moment" in out and "1 done, 0 failed, 0 left of 1" in out

    code, _out, _err = cli("process", "--all", "--from-plugin", "peaks.first-moment@")
    assert code == 2
    code, out, _err = cli("process", "--from-plugin", "peaks.first-moment", "--until", "peaks")
    assert code == 0 and out.count("\tdone\t") == 1
    code, _out, _err = cli("process", "--station", "nowhere")
    assert code == 3


@pytest.mark.slow
def test_dask_info_logs_stay_off_the_terminal(tmp_path: Path) -> None:
    pytest.importorskip("distributed")
    from rasterserver.config import sqlite_url

    settings = Settings(archive=tmp_path / "archive", database_url=sqlite_url(tmp_path / "a"))
    archive, _uids = tpj.many(settings, 2)
    archive.close()
    done = _cli(settings, "process", "--all", "--until", "peaks", "--dask")
    assert done.returncode == 0, describe(done)
    assert done.stdout.count("\tdone\t") == 2
    assert " INFO " not in done.stderr and "distributed." not in done.stderr, done.stderr
    shown = json.loads(_cli(settings, "jobs", "list", "--json").stdout.splitlines()[0])
    assert shown["engine"] == "local-cluster"
    # the workers' files were synced and published together (store/pending.py): a fresh
    # `verify` finds every row's file whole, and no temporary or orphaned file
    checked = _cli(settings, "verify")
    assert checked.returncode == 0, describe(checked)
