"""Catalogue query times with 100,000 acquisitions, on SQLite and PostgreSQL.

Generates the catalogue directly with bulk inserts (no pixel files: this measures SQL only),
then times the two queries a clinic runs all day through `Archive.acquisitions`: one
patient's acquisitions, and acquisitions in a date range (one page of 100, as the CLI and the
API list them, and the whole month). Target: under 50 ms each.

Run: ``.venv/bin/python benchmarks/catalog_queries.py [--acquisitions 100000]``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np
from sqlalchemy import insert, select

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine, write_section
from ingest_rate import _drop_pg, _fresh_pg

from rasterserver.archive import Archive
from rasterserver.catalog.models import Acquisition, Frame, Patient, Visit
from rasterserver.config import Settings, sqlite_url

T0 = dt.datetime(2020, 1, 1, tzinfo=dt.UTC)


def populate(archive: Archive, n: int, patients: int, seed: int = 1) -> None:
    """Insert ``patients`` patients and ``n`` acquisitions (one frame each) over 5 years."""
    rng = np.random.default_rng(seed)
    with archive.engine.begin() as conn:
        conn.execute(
            insert(Patient),
            [{"identifier": f"P{i:06d}", "name": "", "sex": "unknown", "created_at": T0}
             for i in range(patients)],
        )
        pids = [r[0] for r in conn.execute(select(Patient.id).order_by(Patient.id))]
        offsets = np.sort(rng.uniform(0, 5 * 365 * 86400, n))
        owner = rng.integers(0, patients, n)
        batch = 10_000
        for start in range(0, n, batch):
            acq_rows, visit_rows = [], []
            for k in range(start, min(n, start + batch)):
                when = T0 + dt.timedelta(seconds=float(offsets[k]))
                acq_rows.append({
                    "uid": uuid.UUID(int=int(rng.integers(0, 2**62)) << 64 | k).hex,
                    "kind": "patient", "patient_id": pids[owner[k]], "acquired_at": when,
                    "operator": "", "notes": "", "created_at": when,
                })
                visit_rows.append((pids[owner[k]], when.date()))
            conn.execute(insert(Acquisition), acq_rows)
        ids = [r[0] for r in conn.execute(select(Acquisition.id))]
        for start in range(0, len(ids), batch):
            conn.execute(insert(Frame), [
                {"acquisition_id": i, "index": 0, "role": "raster", "height": 604,
                 "width": 576, "dtype": "uint8", "sha256": "0" * 64,
                 "store_path": "raw/x.h5", "dataset": "frames/0"}
                for i in ids[start:start + batch]
            ])
        conn.execute(insert(Visit), [
            {"patient_id": p, "visit_date": d, "notes": ""} for p, d in sorted(set(visit_rows))
        ][:50_000])
    # Fresh statistics, as autovacuum (PostgreSQL) would gather them after a bulk load.
    with archive.engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
        conn.exec_driver_sql("ANALYZE")


def timed(fn, repeat: int = 30) -> float:
    """Median wall time of ``fn()`` in milliseconds (after one warm-up call)."""
    fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1000)
    return statistics.median(times)


def _queries(archive: Archive, who: list[str]) -> tuple[float, float, float, int, float]:
    it = iter(who * 2)
    patient_ms = timed(lambda: archive.acquisitions(patient=next(it)))
    since, until = T0 + dt.timedelta(days=400), T0 + dt.timedelta(days=430)
    page_ms = timed(lambda: archive.acquisitions(since=since, until=until))
    full = len(archive.acquisitions(since=since, until=until, limit=10**6))
    full_ms = timed(
        lambda: archive.acquisitions(since=since, until=until, limit=10**6), repeat=10
    )
    find_ms = timed(lambda: archive.find(since=since, until=until), repeat=10)
    return patient_ms, page_ms, full_ms, full, find_ms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--acquisitions", type=int, default=100_000)
    parser.add_argument("--patients", type=int, default=5_000)
    parser.add_argument("--postgres", default="postgresql+psycopg://postgres@127.0.0.1:5432/test")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args()
    rows = []
    for backend in ("sqlite", "postgresql"):
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp) / "archive"
            url = sqlite_url(root) if backend == "sqlite" else _fresh_pg(args.postgres)
            try:
                with Archive.create(Settings(archive=root, database_url=url)) as archive:
                    t = time.perf_counter()
                    populate(archive, args.acquisitions, args.patients)
                    fill = time.perf_counter() - t
                    rng = np.random.default_rng(2)
                    who = [f"P{i:06d}" for i in rng.integers(0, args.patients, 30)]
                    patient_ms, page_ms, full_ms, full, find_ms = _queries(archive, who)
            finally:
                if backend == "postgresql":
                    _drop_pg(args.postgres, url)
        per_patient = args.acquisitions / args.patients
        rows.append(
            f"| {backend} | {args.acquisitions:,} | {patient_ms:.1f} (~{per_patient:.0f} rows) "
            f"| {page_ms:.1f} | {full_ms:.1f} ({full:,} rows) | {find_ms:.1f} | {fill:.0f} s |"
        )
        print(rows[-1], flush=True)
    body = (
        f"Machine: {machine()}.\n\n"
        f"{args.acquisitions:,} acquisitions (one frame each) of {args.patients:,} patients "
        "over five years, inserted in bulk; median of 30 calls of `Archive.acquisitions` "
        "(ORM objects with their frames and patient loaded), in milliseconds. "
        "Target: under 50 ms.\n\n"
        "| catalogue | acquisitions | one patient's acquisitions | date range, first page "
        "of 100 | date range, whole month | whole month with `Archive.find` | fill time |"
        "\n|---|---|---|---|---|---|---|\n"
        + "\n".join(rows)
        + "\n\n`Archive.acquisitions` builds full ORM objects with their frames (what a page "
        "of the list shows); `Archive.find` returns light summaries from one query (uid, "
        "patient, kind, time, frame count), for searches that return thousands of rows."
        "\n\nScript: `benchmarks/catalog_queries.py`."
    )
    if not args.no_write:
        write_section("Catalogue queries", body)


if __name__ == "__main__":
    main()
