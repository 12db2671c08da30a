"""Processing jobs: in-process engine against a ``LocalCluster`` of two workers (issue 16).

Decides :data:`rasterserver.jobs.LOCAL_CLUSTER_MIN`: whether a job asked for without
``--dask`` should start a local cluster. Each engine gets an archive of its own with the
same N simulated 604x576 acquisitions (SQLite, nothing stored yet) and runs one catalogue
job over them (target mesh): job creation, planning, reading frames, computing, writing
derived files, committing rows and task rows. The cluster's time includes starting and
stopping it, as a user waits for both.

Run: ``nice .venv/bin/python benchmarks/jobs_engine.py [N] [--write]``.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import geometry_truth as gt
from _machine import machine, write_section

from rasterserver.config import Settings, sqlite_url
from rasterserver.processing_jobs import Selection, create_job, run_job


def one(engine: str, count: int, root: Path) -> float:
    """Seconds for a job of ``count`` acquisitions on ``engine``."""
    settings = Settings(archive=root / engine / "archive",
                        database_url=sqlite_url(root / engine / "archive"))
    image = gt.rendering("back").image
    archive, _uids = gt.archive_with_frames(settings, {f"b{i}": image for i in range(count)})
    with archive:
        t0 = time.perf_counter()
        job, _ = create_job(archive, Selection(all=True), targets=["mesh"])
        status = run_job(archive, job.id, dask=engine == "local-cluster")
        spent = time.perf_counter() - t0
        assert status.job.state == "done" and status.job.done == count, status.to_dict()
    return spent


def main() -> None:
    count = int(sys.argv[1]) if len(sys.argv) > 1 and sys.argv[1].isdigit() else 60
    with tempfile.TemporaryDirectory() as tmp:
        times = {engine: one(engine, count, Path(tmp))
                 for engine in ("in-process", "local-cluster")}
    rows = "\n".join(
        f"| {engine} | {count} | {spent:.1f} | {1000 * spent / count:.0f} | "
        f"{count / spent:.1f} |"
        for engine, spent in times.items()
    )
    ratio = times["local-cluster"] / times["in-process"]
    body = f"""{machine()}. `benchmarks/jobs_engine.py {count}`: one catalogue job (target mesh)
over {count} simulated 604×576 acquisitions on SQLite, each engine on a fresh archive; the
cluster's time includes starting and stopping it (2 worker processes, 1 thread each).

| engine | acquisitions | s | ms / acquisition | acquisitions / s |
|---|---|---|---|---|
{rows}

The local cluster took {ratio:.2f}× the in-process time. The coordinator (planning, reading
frames, writing the derived files, committing result and task rows) does most of each
acquisition's work and shares the two cores with the workers, so
`rasterserver.jobs.LOCAL_CLUSTER_MIN` is None: without `--dask` or a scheduler, jobs compute
in the coordinator. `--dask` still starts a local cluster; `--scheduler` /
`RASTERSERVER_DASK_SCHEDULER` use a real one."""
    print(body)
    if "--write" in sys.argv:
        write_section("Processing jobs: in-process or a local cluster", body)


if __name__ == "__main__":
    main()
