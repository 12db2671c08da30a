"""``diff``, ``stats`` and ``prune`` over an archive processed with two chains (issue 16).

N simulated 604x576 acquisitions (the back shifted sideways by a few pixels each, so results
differ) are processed with the default chain and with the peak detector's bias fraction at
0.3, both up to the mesh and the analysis (SQLite). Then timed, each alone: the diff of the
two chains (finding results by provenance, reading the surface, numbered lines and analysis of
both chains for each changed acquisition), ``archive_stats`` with the prune plan, the prune
plan alone, and the prune itself (rows, then files). The archive is built outside the timings.

Run: ``nice .venv/bin/python benchmarks/diff_prune.py [N ≤ 60] [--write]`` (the test
archive helper names acquisitions by minute).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import geometry_truth as gt
import numpy as np
from _machine import machine, write_section

from rasterserver.archive_stats import archive_stats
from rasterserver.chain_diff import diff_chains
from rasterserver.chain_spec import parse_chain
from rasterserver.config import Settings, sqlite_url
from rasterserver.processing_jobs import Selection, create_job, resolve_selection, run_job
from rasterserver.prune import plan_prune, run_prune


def main() -> None:
    count = int(sys.argv[1]) if len(sys.argv) > 1 and sys.argv[1].isdigit() else 40
    image = gt.rendering("back").image
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "archive"
        settings = Settings(archive=root, database_url=sqlite_url(root))
        archive, _uids = gt.archive_with_frames(
            settings, {f"b{i}": np.roll(image, i % 7, axis=1) for i in range(count)})
        with archive:
            t0 = time.perf_counter()
            for params in ({"peaks": {"bias_fraction": 0.3}}, None):
                job, _ = create_job(archive, Selection(all=True), params=params)
                assert run_job(archive, job.id, dask=False).job.state == "done"
            build = time.perf_counter() - t0
            selected = resolve_selection(archive, Selection(all=True))
            t0 = time.perf_counter()
            report = diff_chains(archive, parse_chain("default"),
                                 parse_chain("peaks.bias_fraction=0.3"), selected)
            t_diff = time.perf_counter() - t0
            assert len(report.by_status("changed")) == count
            t0 = time.perf_counter()
            stats = archive_stats(archive, prune=True)
            t_stats = time.perf_counter() - t0
            t0 = time.perf_counter()
            plan = plan_prune(archive, keep_jobs=0)
            t_plan = time.perf_counter() - t0
            t0 = time.perf_counter()
            done = run_prune(archive, plan)
            t_prune = time.perf_counter() - t0
    load = os.getloadavg()[0]
    rows = [
        ("diff of two chains (8 stages each)", t_diff),
        ("stats with the prune plan", t_stats),
        ("prune plan alone", t_plan),
        ("prune: rows, then files", t_prune),
    ]
    body = "\n".join([
        f"Machine: {machine()}; load average {load:.1f} at the end (the machine is shared "
        "with other sessions: figures are upper bounds).",
        "",
        f"{count} acquisitions processed with two chains ({build:.0f} s to build, not timed); "
        f"{stats.counts['results']} stored results, {stats.total_bytes / 2**20:.0f} MiB; "
        f"prune removed {done.rows_removed} results and freed "
        f"{done.bytes_freed / 2**20:.0f} MiB (`benchmarks/diff_prune.py {count}`).",
        "",
        "| step | total | per acquisition |",
        "|---|---|---|",
        *(f"| {name} | {t:.2f} s | {1000 * t / count:.1f} ms |" for name, t in rows),
    ])
    print(body)
    if "--write" in sys.argv:
        write_section("What changed and space: diff, stats, prune", body)


if __name__ == "__main__":
    main()
