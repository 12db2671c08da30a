"""Load on the HTTP API over loopback: many readers, then many uploading stations.

1. Readers: the catalogue holds 100,000 acquisitions (bulk-inserted with
   ``catalog_queries.populate``, no pixel files); ``--clients`` concurrent clients (default
   50) list one patient's acquisitions, list a date range (first page of 100), fetch one
   acquisition's metadata and one patient, in a loop, for ``--seconds`` (default 60). Every
   request is authenticated and audited (one audit row per patient touched, committed before
   the response). Reported: requests/s, latency percentiles, errors (non-2xx or transport).
2. Stations: ``--stations`` concurrent station accounts (default 20) each upload
   ``--uploads`` acquisitions of one 604x576 uint8 frame (a distinct random frame each).
   Afterwards every upload must be in the catalogue exactly once with the SHA-256 of the
   frame that was sent, and ``Archive.verify()`` must re-hash every stored frame clean.

The server runs as ``rasterserver serve`` in its own process (``--workers``); the clients
run here with asyncio + httpx, on the same machine (so they compete for its cores).
Only loopback traffic; every loop is bounded by time or count.

Run: ``.venv/bin/python benchmarks/api_load.py [--postgres URL] [--no-write]``.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime as dt
import io
import os
import random
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
from sqlalchemy import select

from rasterserver.api import auth
from rasterserver.archive import Archive
from rasterserver.catalog.auth_models import AuditEvent
from rasterserver.catalog.models import Acquisition
from rasterserver.config import Settings, sqlite_url
from rasterserver.store.hashing import frame_sha256

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _fresh_pg(admin_url: str) -> str:
    """Create an empty PostgreSQL database next to ``admin_url``'s and return its URL."""
    import uuid

    from sqlalchemy import text
    from sqlalchemy.engine import make_url

    from rasterserver.catalog.database import make_engine

    name = f"rs_bench_{uuid.uuid4().hex[:8]}"
    engine = make_engine(admin_url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    engine.dispose()
    return make_url(admin_url).set(database=name).render_as_string(hide_password=False)


def _drop_pg(admin_url: str, url: str) -> None:
    """Drop the database made by :func:`_fresh_pg`."""
    from sqlalchemy import text
    from sqlalchemy.engine import make_url

    from rasterserver.catalog.database import make_engine

    engine = make_engine(admin_url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{make_url(url).database}" WITH (FORCE)'))
    engine.dispose()


try:
    import ingest_rate  # noqa: F401  (catalog_queries imports its PostgreSQL helpers)
except ImportError:
    # ingest_rate may not import (it needs helpers of its own); catalog_queries only wants
    # the two PostgreSQL helpers from it, so hand it ours
    import types

    _stub = types.ModuleType("ingest_rate")
    _stub._fresh_pg, _stub._drop_pg = _fresh_pg, _drop_pg  # type: ignore[attr-defined]
    sys.modules["ingest_rate"] = _stub

from _machine import machine, write_section  # noqa: E402
from catalog_queries import T0, populate  # noqa: E402


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(settings: Settings, workers: int,
           log: Path) -> tuple[subprocess.Popen[bytes], str]:
    port = _free_port()
    cmd = [sys.executable, "-m", "rasterserver", "--archive", str(settings.archive),
           "--database-url", settings.database_url, "serve", "--host", "127.0.0.1",
           "--port", str(port), "--workers", str(workers), "--log-level", "warning"]
    # the server's log goes to a file: an unread pipe would fill and stall the server
    server = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log.open("wb"),
                              env=os.environ | {"RASTERSERVER_REQUEST_TIMEOUT": "300"})
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            httpx.get(url + "/health", timeout=2).raise_for_status()
            return server, url
        except httpx.HTTPError:
            if server.poll() is not None:
                raise RuntimeError(log.read_text()) from None
            time.sleep(0.3)
    server.kill()
    raise RuntimeError("server did not start")


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))]


async def _readers(url: str, token: str, clients: int, seconds: float, uids: list[str],
                   patients: list[str]) -> tuple[list[float], int, int, dict[str, int]]:
    latencies: list[float] = []
    errors = 0
    kinds: dict[str, int] = {}
    failures: dict[str, int] = {}
    samples: list[str] = []
    stop = time.monotonic() + seconds
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=url, headers={"Authorization": f"Bearer {token}"},
                                 limits=limits, timeout=120) as client:

        async def one(seed: int) -> None:
            nonlocal errors
            rng = random.Random(seed)
            while time.monotonic() < stop:
                kind = rng.choice(("patient-list", "range-page", "acquisition", "patient"))
                if kind == "patient-list":
                    req = ("/acquisitions", {"patient": rng.choice(patients), "limit": 100})
                elif kind == "range-page":
                    start = T0 + dt.timedelta(days=rng.uniform(0, 5 * 365 - 30))
                    req = ("/acquisitions", {"since": start.isoformat(), "until":
                                             (start + dt.timedelta(days=30)).isoformat()})
                elif kind == "acquisition":
                    req = (f"/acquisitions/{rng.choice(uids)}", {})
                else:
                    req = (f"/patients/{rng.choice(patients)}", {})
                t = time.perf_counter()
                try:
                    response = await client.get(req[0], params=req[1])
                    ok = response.status_code == 200
                    why = str(response.status_code)
                    if not ok and len(samples) < 5:
                        samples.append(f"{kind} {response.status_code} {response.text[:200]}")
                except httpx.HTTPError as exc:
                    ok, why = False, type(exc).__name__
                if not ok:
                    failures[why] = failures.get(why, 0) + 1
                latencies.append(time.perf_counter() - t)
                kinds[kind] = kinds.get(kind, 0) + 1
                errors += not ok

        await asyncio.gather(*(one(i) for i in range(clients)))
    if failures:
        print("reader failures:", failures, *samples, sep="\n  ", flush=True)
    kinds |= {f"failed {k}": v for k, v in failures.items()}
    return latencies, errors, len(latencies), kinds


async def _stations(url: str, tokens: list[str], uploads: int,
                    patients: list[str]) -> tuple[dict[str, str], list[float], int]:
    stored: dict[str, str] = {}  # uid -> sha256 of the frame sent
    latencies: list[float] = []
    errors = 0

    async def station(k: int, token: str) -> None:
        nonlocal errors
        rng = np.random.default_rng(1000 + k)
        async with httpx.AsyncClient(base_url=url, timeout=300,
                                     headers={"Authorization": f"Bearer {token}"}) as client:
            for i in range(uploads):
                image = rng.integers(0, 256, (604, 576), dtype=np.uint8)
                buffer = io.BytesIO()
                np.save(buffer, image, allow_pickle=False)
                t = time.perf_counter()
                try:
                    response = await client.post(
                        "/acquisitions", files=[("files", (f"s{k}-{i}.npy", buffer.getvalue()))],
                        data={"patient": patients[(k * uploads + i) % len(patients)]})
                except httpx.HTTPError:
                    errors += 1
                    continue
                latencies.append(time.perf_counter() - t)
                if response.status_code != 201:
                    errors += 1
                    continue
                uid = response.json()["uid"]
                if uid in stored:
                    errors += 1
                stored[uid] = frame_sha256(image)

    await asyncio.gather(*(station(k, t) for k, t in enumerate(tokens)))
    return stored, latencies, errors


def run(backend: str, args: argparse.Namespace) -> dict[str, object]:
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        root = Path(tmp) / "archive"
        url = sqlite_url(root) if backend == "sqlite" else _fresh_pg(args.postgres)
        try:
            settings = Settings(archive=root, database_url=url)
            with Archive.create(settings) as archive:
                t = time.perf_counter()
                populate(archive, args.acquisitions, args.patients)
                fill = time.perf_counter() - t
                auth.add_account(archive, "reader", role="clinician")
                reader = auth.create_token(archive, "reader")
                stations = []
                for k in range(args.stations):
                    auth.add_account(archive, f"station-{k}", role="station", kind="service")
                    stations.append(auth.create_token(archive, f"station-{k}"))
                with archive.session() as s:
                    uids = list(s.scalars(select(Acquisition.uid).limit(20_000)))
                rng = random.Random(3)
                patients = [f"P{rng.randrange(args.patients):06d}" for _ in range(500)]
            server_log = Path(tmp) / "server.log"
            server, base = _start(settings, args.workers, server_log)
            try:
                lat, errors, n, kinds = asyncio.run(
                    _readers(base, reader, args.clients, args.seconds, uids, patients))
                t = time.perf_counter()
                stored, up_lat, up_errors = asyncio.run(
                    _stations(base, stations, args.uploads, patients))
                up_wall = time.perf_counter() - t
            finally:
                server.terminate()
                server.wait(timeout=60)
                if server_log.stat().st_size:
                    print("server log (tail):", server_log.read_text()[-3000:], flush=True)
            with Archive(settings) as archive:
                with archive.session() as s:
                    rows = s.execute(
                        select(Acquisition.uid).where(Acquisition.uid.in_(list(stored)))
                    ).all()
                    audit_rows = len(s.scalars(select(AuditEvent.id)).all())
                found = {uid: archive.acquisition(uid).frames[0].sha256 for (uid,) in rows}
                t = time.perf_counter()
                report = archive.verify()
                verify_s = time.perf_counter() - t
        finally:
            if backend == "postgresql":
                _drop_pg(args.postgres, url)
    expected = args.stations * args.uploads
    return {
        "backend": backend, "fill": fill, "requests": n, "errors": errors,
        "rps": n / args.seconds, "p50": 1000 * statistics.median(lat),
        "p95": 1000 * _percentile(lat, 95), "p99": 1000 * _percentile(lat, 99),
        "max": 1000 * max(lat), "kinds": kinds, "uploads_expected": expected,
        "uploads_ok": len(stored), "upload_errors": up_errors,
        "stored_once": len(rows) == len(stored) == len(found),
        "checksums_match": all(found.get(u) == sha for u, sha in stored.items()),
        # the bulk-inserted rows have no files by design ("missing"); anything about an
        # upload, or any orphaned, temporary or stray file, is a real problem
        "verify_ok": not [p for p in report.problems
                          if p.uid in stored or p.kind != "missing"],
        "verified_frames": report.frames_checked,
        "verify_s": verify_s, "upload_wall": up_wall,
        "upload_p50": 1000 * statistics.median(up_lat) if up_lat else float("nan"),
        "upload_p99": 1000 * _percentile(up_lat, 99) if up_lat else float("nan"),
        "audit_rows": audit_rows,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--acquisitions", type=int, default=100_000)
    parser.add_argument("--patients", type=int, default=5_000)
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--stations", type=int, default=20)
    parser.add_argument("--uploads", type=int, default=10, help="acquisitions per station")
    parser.add_argument("--workers", type=int, default=2, help="uvicorn worker processes")
    parser.add_argument("--postgres", default=None,
                        help="also run on PostgreSQL (admin URL of a server)")
    parser.add_argument("--dir", default=None, help="folder for the temporary archive")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args()
    load = os.getloadavg()[0]
    results = []
    for backend in ("sqlite", *(("postgresql",) if args.postgres else ())):
        r = run(backend, args)
        print(r, flush=True)
        results.append(r)
    def failures(r: dict[str, object]) -> str:
        kinds = {k[7:]: v for k, v in r["kinds"].items() if k.startswith("failed ")}  # type: ignore[union-attr]
        return f"{r['errors']}" + (f" ({', '.join(f'{v} {k}' for k, v in kinds.items())})"
                                   if kinds else "")

    rows_read = "\n".join(
        f"| {r['backend']} | {r['requests']:,} | {r['rps']:.0f} | {r['p50']:.0f} | "
        f"{r['p95']:.0f} | {r['p99']:.0f} | {r['max']:.0f} | {failures(r)} |" for r in results)
    rows_up = "\n".join(
        f"| {r['backend']} | {r['uploads_ok']} / {r['uploads_expected']} | {r['upload_errors']} "
        f"| {r['upload_wall']:.1f} s ({r['uploads_ok'] / r['upload_wall']:.1f}/s) | "
        f"{r['upload_p50']:.0f} / {r['upload_p99']:.0f} | "
        f"{'yes' if r['stored_once'] and r['checksums_match'] else 'NO'} | "
        f"{'clean' if r['verify_ok'] else 'PROBLEMS'} ({r['verified_frames']:,} frames, "
        f"{r['verify_s']:.1f} s) |" for r in results)
    body = (
        f"Machine: {machine()}. Load average before the run: {load:.1f} (the machine was "
        "shared with other jobs; server and clients ran on the same cores).\n\n"
        f"Server: `rasterserver serve --workers {args.workers}` on loopback; every request "
        "authenticated (token digest look-up) and audited (one append-only row per patient "
        "touched, committed before the response starts).\n\n"
        f"**Readers**: {args.acquisitions:,} acquisitions of {args.patients:,} patients "
        f"catalogued; {args.clients} concurrent clients for {args.seconds:.0f} s, each looping "
        "over: one patient's acquisitions (up to 100), a 30-day range (first page of 100), one "
        "acquisition's metadata, one patient. Latency in ms.\n\n"
        "| catalogue | requests | req/s | p50 | p95 | p99 | max | errors |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|\n" + rows_read + "\n\n"
        f"**Stations**: {args.stations} concurrent station accounts, {args.uploads} uploads "
        "each of one 604x576 uint8 frame (NPY, multipart). Checked afterwards: every upload "
        "in the catalogue exactly once with the SHA-256 of the frame sent, and "
        "`Archive.verify()` re-hashing every stored frame (clean = no problem with an upload and "
        "no orphaned, temporary or stray file; the bulk-inserted rows have no files by "
        "design and are left out).\n\n"
        "| catalogue | stored | errors | wall time | latency p50 / p99 (ms) | once, checksums "
        "equal | verify |\n|---|---:|---:|---:|---:|---|---|\n" + rows_up + "\n\n"
        "Reading the numbers: each read costs a token look-up, the catalogue query (with "
        "frames and patient), JSON for up to 100 acquisitions, and an audit transaction "
        "(up to 100 rows, committed and, on SQLite, fsynced before the response starts). "
        "The server's two workers share the two cores with the 50 asyncio clients and with "
        "other jobs, so the throughput is CPU-bound and the tail latencies are mostly queueing; "
        "on a dedicated machine with the clients elsewhere expect several times more. "
        "A transport error (ReadError) is a keep-alive connection the server closed while the "
        "client reused it; `serve --keep-alive` (30 s default) makes it rare.\n\n"
        "Script: `benchmarks/api_load.py`."
    )
    if not args.no_write:
        write_section("HTTP API", body)
    print(body)


if __name__ == "__main__":
    main()
