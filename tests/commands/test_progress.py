"""The CLI's progress bar: rate and ETA on stderr on a terminal, nothing in a pipe."""

from __future__ import annotations

import io
import sys
import time

from rasterserver.commands.progress import duration, progress_bar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_bar_on_a_terminal_with_rate_and_eta(monkeypatch) -> None:
    screen = Terminal()
    monkeypatch.setattr(sys, "stderr", screen)
    with progress_bar("comparing") as progress:
        for done in range(1, 6):
            time.sleep(0.02)
            progress(done, 10)
    shown = screen.getvalue()
    assert "comparing" in shown and "acq/s" in shown and "ETA 0:0" in shown


def test_nothing_in_a_pipe_or_when_quiet(monkeypatch) -> None:
    pipe = io.StringIO()
    monkeypatch.setattr(sys, "stderr", pipe)
    for enabled in (True, False):
        with progress_bar("comparing", enabled=enabled) as progress:
            progress(1, 2)
    assert pipe.getvalue() == ""
    monkeypatch.setattr(sys, "stderr", Terminal())
    with progress_bar("comparing", enabled=False) as progress:
        progress(1, 2)
    assert sys.stderr.getvalue() == ""


def test_duration() -> None:
    assert duration(None) == "?" and duration(61.4) == "1:01" and duration(3725) == "1:02:05"


def test_a_jobs_bar_shows_its_counts_rate_and_eta(monkeypatch) -> None:
    from rasterserver.catalog.job_models import ProcessingJob
    from rasterserver.commands.jobs import job_progress
    from rasterserver.processing_jobs import JobStatus

    screen = Terminal()
    monkeypatch.setattr(sys, "stderr", screen)
    job = ProcessingJob(id="abcdef0123456789" * 2, total=10, done=3, failed=1, state="running")
    with job_progress() as progress:
        progress(JobStatus(job, left=6, rate=2.5, eta_s=2.4))
    shown = screen.getvalue()
    assert "job abcdef01 (1 failed)" in shown and "2.5 acq/s" in shown and "ETA 0:02" in shown
