"""Ingest rate end to end: decode + validate, HDF5 written and fsynced, hashed, row committed.

Run: ``.venv/bin/python benchmarks/ingest_rate.py [--frames 400] [--postgres URL]``.
Writes the "Ingest rate" section of BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import io
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine, write_section

from rasterserver.archive import AcquisitionSpec, Archive, FrameSource
from rasterserver.config import Settings, sqlite_url


def raster_like_frame(seed: int, shape: tuple[int, int] = (604, 576)) -> np.ndarray:
    """A stand-in camera frame: bright horizontal lines, one per 10 rows, on noise."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    bend = 6.0 * np.sin(cols / shape[1] * np.pi) * (1 + 0.2 * rng.standard_normal())
    lines = np.exp(-0.5 * ((((rows - bend) % 10.0) - 5.0) / 1.1) ** 2)
    image = 20 + 180 * lines + rng.normal(0, 2.0, shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _npy(frame: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, frame)
    return buf.getvalue()


def measure(settings: Settings, frames: int, mode: str) -> float:
    """Ingest ``frames`` 604x576 uint8 frames in the given mode; return frames/s.

    Modes: ``single`` (one 1-frame acquisition after another), ``six`` (6-frame
    acquisitions, like the seed's calibration), ``stations`` (8 threads ingesting 1-frame
    acquisitions concurrently, as stations uploading to one server), ``batch``
    (``ingest_many`` of 50 acquisitions with 8 writer threads, as when importing a backlog).
    """
    payloads = [_npy(raster_like_frame(i)) for i in range(8)]

    def source(k: int) -> FrameSource:
        return FrameSource(payloads[k % len(payloads)], name="f.npy")

    with Archive.create(settings) as archive:
        archive.add_patient("BENCH")
        start = time.perf_counter()
        if mode == "single":
            for k in range(frames):
                archive.ingest([source(k)], patient="BENCH")
        elif mode == "six":
            for k in range(0, frames, 6):
                archive.ingest([source(k + j) for j in range(6)], patient="BENCH")
        elif mode == "stations":
            with ThreadPoolExecutor(8) as pool:
                list(pool.map(lambda k: archive.ingest([source(k)], patient="BENCH"),
                              range(frames)))
        elif mode == "batch":
            for k in range(0, frames, 50):
                specs = [AcquisitionSpec(frames=[source(k + j)], patient="BENCH")
                         for j in range(50)]
                archive.ingest_many(specs, workers=8)
        elapsed = time.perf_counter() - start
        count = sum(len(a.frames) for a in archive.acquisitions(limit=10**6))
    return count / elapsed


MODES = {
    "single": "one 1-frame acquisition at a time",
    "six": "6-frame acquisitions, one at a time",
    "stations": "8 concurrent stations, 1-frame acquisitions",
    "batch": "`ingest_many`, 50 acquisitions per batch, 8 writer threads",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--postgres", default="postgresql+psycopg://postgres@127.0.0.1:5432/test")
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args()
    rows = []
    for backend in ("sqlite", "postgresql"):
        for mode, what in MODES.items():
            with tempfile.TemporaryDirectory() as tmp:
                root = Path(tmp) / "archive"
                url = sqlite_url(root) if backend == "sqlite" else _fresh_pg(args.postgres)
                rate = measure(Settings(archive=root, database_url=url), args.frames, mode)
                if backend == "postgresql":
                    _drop_pg(args.postgres, url)
            rows.append(f"| {backend} | {what} | {args.frames} | {rate:.0f} |")
            print(rows[-1], flush=True)
    body = (
        f"Machine: {machine()}.\n\n"
        "604×576 uint8 frames sent as NPY bytes through `Archive.ingest`: decoded and "
        "validated, written to a new HDF5 file (default compression), fsynced, renamed, "
        "directory fsynced, SHA-256 in the file and the catalogue, catalogue row committed "
        "(SQLite in WAL mode with `synchronous=FULL`). Target: ≥ 200 frames/s.\n\n"
        "| catalogue | how | frames | frames/s |\n|---|---|---|---|\n"
        + "\n".join(rows)
        + "\n\nReading: the cost is durability, not pixels. Each acquisition is one HDF5 "
        "file, and making it durable before its row is committed takes 3-4 fsyncs (file, "
        "its folder after the rename, new shard folders) plus the catalogue's commit, about "
        "4 ms each on this disk. So the rate in frames/s grows with the frames per "
        "acquisition: the target of 200 frames/s is met with the seed's 6-frame "
        "acquisitions, and not by single-frame acquisitions ingested one at a time, which "
        "are bounded by ~12-16 ms of flushes each. Concurrent stations and `ingest_many` "
        "overlap the flushes of different files. Dropping the fsyncs would be faster and is "
        "deliberately not offered: a committed row must never point at a file a power cut "
        "can take back."
        + "\n\nScript: `benchmarks/ingest_rate.py`."
    )
    if not args.no_write:
        write_section("Ingest rate", body)


def _fresh_pg(admin_url: str) -> str:
    import uuid

    from sqlalchemy import text
    from sqlalchemy.engine import make_url

    from rasterserver.catalog.database import make_engine

    name = f"rs_bench_{uuid.uuid4().hex[:8]}"
    eng = make_engine(admin_url, isolation_level="AUTOCOMMIT")
    with eng.connect() as c:
        c.execute(text(f'CREATE DATABASE "{name}"'))
    eng.dispose()
    return make_url(admin_url).set(database=name).render_as_string(hide_password=False)


def _drop_pg(admin_url: str, url: str) -> None:
    from sqlalchemy import text
    from sqlalchemy.engine import make_url

    from rasterserver.catalog.database import make_engine

    eng = make_engine(admin_url, isolation_level="AUTOCOMMIT")
    with eng.connect() as c:
        c.execute(text(f'DROP DATABASE IF EXISTS "{make_url(url).database}" WITH (FORCE)'))
    eng.dispose()


if __name__ == "__main__":
    main()
