"""Time a patient's trends and comparison when VP must be carried to half of the visits.

A SQLite archive of ``--visits`` processed acquisitions of one clinic patient alternating
the kept frames of clinic tuning person 1 (``tests/data/scenes/person-1-{A,E}.npz``: at A
hair hides the nape and the analysis refuses VP, at E it finds it), so that every other
visit needs VP carried. Timed: :func:`rasterserver.visit_comparison.trend_visits` (what
``GET /patients/{id}/trends`` runs) three times (the first computes and stores the
comparisons carrying needs, the others reuse them), and ``compare_visits`` (what
``rasterserver compare --patient`` runs) once.

Usage::

    python benchmarks/carried_trends.py --visits 10
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

KEPT = Path(__file__).resolve().parent.parent / "tests" / "data" / "scenes"


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    from rasterserver.archive import Archive
    from rasterserver.config import Settings, sqlite_url
    from rasterserver.pipeline import Pipeline
    from rasterserver.simulated_visits import SimulatedVisit, archive_visits
    from rasterserver.simulator.body import clinic_station, random_body
    from rasterserver.visit_comparison import compare_visits, trend_visits

    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--visits", type=int, default=10, help="acquisitions of the patient (≥ 2)")
    args = ap.parse_args(argv)
    if args.visits < 2:
        ap.error("--visits must be at least 2")
    kept = {role: np.load(KEPT / f"person-1-{role}.npz") for role in "AE"}
    station = clinic_station(int(kept["A"]["seed"]), str(kept["A"]["code"]))
    roles = ["A" if k % 2 == 0 else "E" for k in range(args.visits)]
    back = random_body(1).back
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "archive"
        settings = Settings(archive=root, database_url=sqlite_url(root))
        with Archive.create(settings) as archive:
            visits = [SimulatedVisit(back, kept[r]["image"]) for r in roles]
            rows = archive_visits(
                archive, visits, station=station, patient="P-1", station_name="clinic"
            )
            pipeline = Pipeline(archive)
            for row in rows:
                pipeline.process(row.uid, until="mesh")
                pipeline.process(row.uid, until="analysis")
            for run in range(3):
                t0 = time.perf_counter()
                got = trend_visits(pipeline, "P-1")
                seconds = time.perf_counter() - t0
                carried = sum(
                    1 for _, _, p in got if p and any("vp_carried_from" in e for e in p.values())
                )
                print(
                    f"trends, run {run + 1}: {seconds:.2f} s; VP carried to {carried} of "
                    f"{roles.count('A')} visits without their own"
                )
            t0 = time.perf_counter()
            document = compare_visits(pipeline, [r.uid for r in rows], Path(tmp) / "cmp")
            seconds = time.perf_counter() - t0
            carried = sum("from" in c for c in document["carried_vp"].values())
            print(
                f"compare --patient: {seconds:.2f} s ({len(document['pairs'])} pairs); VP "
                f"carried to {carried} of {roles.count('A')}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
