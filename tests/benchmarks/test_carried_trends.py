"""The carried-VP timing benchmark run as users run it (a fresh process)."""

from __future__ import annotations

from bench_scripts import run_script


def test_two_visits_one_without_vp_are_timed_and_carried() -> None:
    done = run_script("carried_trends", "--visits", "2")
    assert done.returncode == 0, done.stderr[-2000:]
    assert "trends, run 1:" in done.stdout and "VP carried to 1 of 1" in done.stdout
    assert "compare --patient:" in done.stdout
    bad = run_script("carried_trends", "--visits", "1")
    assert bad.returncode == 2 and "at least 2" in bad.stderr
