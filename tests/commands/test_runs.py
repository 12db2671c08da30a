"""``rasterserver runs``: listing an acquisition's runs, and marking runs of killed processes."""

from __future__ import annotations

import json
import subprocess

import geometry_truth as gt
import pytest

from rasterserver.catalog.models import PipelineRun
from rasterserver.cli import main
from rasterserver.config import Settings
from rasterserver.pipeline import INTERRUPTED
from rasterserver.runner import current_runner, local_host


def _dead_runner() -> str:
    child = subprocess.Popen(["true"])
    child.wait()
    return f"{local_host()}:{child.pid}"


@pytest.fixture
def setup(settings: Settings):
    """An acquisition with a run of a killed local process, one of a live process and one
    of another host, all stored as running."""
    archive, uids = gt.archive_with_frames(settings, {"back": gt.rendering("back").image})
    acquisition = archive.acquisition(uids["back"])
    with archive.session() as s:
        for host, runner in [(local_host(), _dead_runner()), (local_host(), current_runner()),
                             ("elsewhere.invalid", "elsewhere.invalid:7@b/1")]:
            s.add(PipelineRun(acquisition_id=acquisition.id, chain=[], status="running",
                              host=host, runner=runner))
    archive.close()
    base = ["--archive", str(settings.archive), "--database-url", settings.database_url]

    def run(*args: str) -> int:
        return main([*base, *args])

    return run, uids["back"]


def test_reap_marks_the_runs_of_gone_processes_and_says_how_many(setup, capsys) -> None:
    cli, uid = setup
    assert cli("runs", "reap", "--dry-run") == 0
    out, err = capsys.readouterr()
    assert out.startswith("1 interrupted run(s) would be marked failed")
    assert "1 run(s) of live processes" in out
    assert "elsewhere.invalid (1)" in err and "--host" in err
    assert cli("runs", "reap") == 0
    assert capsys.readouterr().out.startswith("1 interrupted run(s) marked failed")
    assert cli("runs", "reap") == 0
    assert capsys.readouterr().out.startswith("0 interrupted run(s) marked")
    assert cli("runs", "reap", "--host", "elsewhere.invalid") == 0
    out, err = capsys.readouterr()
    assert out.startswith("1 interrupted run(s) marked failed") and not err
    output = out + err
    assert "P1" not in output and uid not in output  # nothing about patients or acquisitions

    assert cli("runs", "list", uid, "--json") == 0
    runs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["status"] for r in runs] == ["failed", "running", "failed"]
    assert runs[0]["error"].startswith(f"{INTERRUPTED}the process running it ({local_host()}:")
    assert runs[2]["error"].startswith(f"{INTERRUPTED}host elsewhere.invalid")


def test_listing_shows_a_killed_run_as_interrupted(setup, capsys) -> None:
    cli, uid = setup
    assert cli("runs", "list", uid) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split("\t")[1] for line in lines] == ["failed", "running", "running"]
    assert INTERRUPTED in lines[0]
    assert cli("runs", "list", "no-such-uid") == 3


def test_help_explains_reap(capsys) -> None:
    assert main(["runs", "reap", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "killed" in text and "--host" in text and "interrupted:" in text
