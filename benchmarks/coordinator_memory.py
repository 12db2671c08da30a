"""What a job's coordinator keeps in memory per acquisition (issue 16: memory bounded).

For each N, one catalogue job (target mesh) over the cached archive of N acquisitions of
``benchmarks/reprocess.py`` (built here when missing) on a ``LocalCluster`` of two workers,
as ``rasterserver process --all`` runs it. :mod:`tracemalloc` (numpy's arrays included)
snapshots the coordinator's Python memory before and after :func:`run_job`; printed per N:
the memory traced after the job and its peak during the job, what the scheduler and the
client still hold (tasks, futures), and the largest allocations retained since the start.
Memory that grows with the acquisitions would show as traced memory growing with N.

Run: ``nice .venv/bin/python benchmarks/coordinator_memory.py 1000 3000``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import gc  # noqa: E402
import sys  # noqa: E402
import tracemalloc  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from reprocess import _warm, build, reset  # noqa: E402

from rasterserver.archive import Archive  # noqa: E402
from rasterserver.jobs import dask_client  # noqa: E402
from rasterserver.processing_jobs import Selection, create_job, run_job  # noqa: E402


def _scheduler_tasks(dask_scheduler: Any) -> int:
    return len(dask_scheduler.tasks)


def measure(cache: Path, count: int, top: int) -> None:
    """One job over ``count`` acquisitions, its retained memory printed."""
    settings = build(cache / f"n{count}", count)
    reset(settings)
    with dask_client(n_workers=2) as client:
        client.run(_warm)
        with Archive(settings) as archive:
            job, _ = create_job(archive, Selection(all=True), targets=["mesh"])
            gc.collect()
            tracemalloc.start(12)
            before = tracemalloc.take_snapshot()
            run_job(archive, job.id, client=client)
            gc.collect()
            after = tracemalloc.take_snapshot()
            now, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            print(f"N={count}: traced after the job {now / 1e6:.1f} MB, peak {peak / 1e6:.1f} MB; "
                  f"scheduler tasks {client.run_on_scheduler(_scheduler_tasks)}, "
                  f"client futures {len(client.futures)}")
            for stat in after.compare_to(before, "traceback")[:top]:
                frame = stat.traceback[-1]
                print(f"  {stat.size_diff / 1e6:+.2f} MB in {stat.count_diff:+d} blocks, "
                      f"{frame.filename}:{frame.lineno}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("counts", type=int, nargs="*", default=[1000, 3000])
    parser.add_argument("--cache", type=Path, default=Path("/tmp/rasterserver-reprocess"))
    parser.add_argument("--top", type=int, default=5)
    args = parser.parse_args()
    for count in args.counts:
        measure(args.cache, count, args.top)


if __name__ == "__main__":
    main()
