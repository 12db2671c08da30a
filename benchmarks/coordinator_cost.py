"""The coordinator's CPU per acquisition in an in-process job, apart from the computing.

Runs one catalogue job (target mesh) in-process over the cached archive of
``benchmarks/reprocess.py`` (build it with ``reprocess.py N --engines ''`` first) and times
with ``time.process_time`` what the coordinator does around :func:`rasterserver.worker.work`:
planning (``Pipeline.plan_many`` / ``plan``), committing rows (``Pipeline.commit_many``) and
the rest of the loop (task pages, task states, polling the job's state). No profiler: it would
inflate the small calls most.

Run: ``nice .venv/bin/python benchmarks/coordinator_cost.py [N]`` (N cached, default 250).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from reprocess import reset, settings_for  # noqa: E402

import rasterserver.engines as engines  # noqa: E402
from rasterserver.archive import Archive  # noqa: E402
from rasterserver.pipeline import Pipeline  # noqa: E402
from rasterserver.processing_jobs import Selection, create_job, run_job  # noqa: E402

spent: dict[str, float] = {}


def _timed(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        start = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            spent[name] = spent.get(name, 0.0) + time.process_time() - start

    return wrapper


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument(
        "count", type=int, nargs="?", default=250,
        help="acquisitions in the cached archive of reprocess.py (build it first)",
    )  # fmt: skip
    count = ap.parse_args(argv).count
    settings = settings_for(Path("/tmp/rasterserver-reprocess") / f"n{count}")
    reset(settings)
    engines.work = _timed("work", engines.work)  # type: ignore[assignment]
    for name in ("plan_many", "plan", "commit_many"):
        setattr(Pipeline, name, _timed(name, getattr(Pipeline, name)))
    with Archive(settings) as archive:
        job, _ = create_job(archive, Selection(all=True), targets=["mesh"])
        start = time.process_time()
        run_job(archive, job.id, dask=False)
        total = time.process_time() - start
    rest = total - sum(spent.values())
    parts = ", ".join(f"{name} {1000 * value / count:.2f}" for name, value in spent.items())
    coordinator = (total - spent.get("work", 0.0)) / count * 1000
    print(f"{count} acquisitions: CPU ms/acquisition: total {1000 * total / count:.1f}; {parts}; "
          f"rest of the loop {1000 * rest / count:.2f}; coordinator (all but work) "
          f"{coordinator:.2f}")


if __name__ == "__main__":
    main()
