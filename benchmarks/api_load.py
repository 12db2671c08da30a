"""Load on the HTTP API over loopback: many readers, then many uploading stations.

1. Readers: the catalogue holds 100,000 acquisitions (bulk-inserted with
   ``catalog_queries.populate``, no pixel files). The load comes from ``wrk`` (a C program,
   run as its own process): 2 threads, ``--clients`` keep-alive connections (default 50),
   closed loop, for ``--seconds`` (default 60). Each request is drawn at random from a few
   thousand paths pre-generated here with a fixed seed and handed to wrk in a Lua script:
   one patient's acquisitions (up to 100), a date range (first page of 100), one
   acquisition's metadata, one patient (``--mix`` keeps one kind only). Every request is
   authenticated and audited (one audit event per request, linked to every patient it
   touched, committed before the response). Reported: requests/s, wrk's latency
   percentiles, errors (HTTP error status or socket error).
2. Stations: ``--stations`` concurrent station accounts (default 20) each upload
   ``--uploads`` acquisitions of one 604x576 uint8 frame (a distinct random frame each),
   with asyncio + httpx clients in this process. Afterwards every upload must be in the
   catalogue exactly once with the SHA-256 of the frame that was sent, and
   ``Archive.verify()`` must re-hash every stored frame clean.

The server runs as ``rasterserver serve`` in its own process (``--workers``), on the same
machine as the load (so they compete for its cores). Needs ``wrk`` (``apt-get install wrk``).
Only loopback traffic; every loop is bounded by time or count.

Run: ``.venv/bin/python benchmarks/api_load.py [--postgres URL] [--mix KIND] [--no-write]``.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime as dt
import io
import json
import os
import random
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import quote, urlencode

import httpx
import numpy as np
from sqlalchemy import select

from rasterserver.archive import Archive
from rasterserver.catalog.auth_models import AuditEvent
from rasterserver.catalog.models import Acquisition
from rasterserver.config import Settings, sqlite_url
from rasterserver.services import auth
from rasterserver.store.hashing import frame_sha256

sys.path.insert(0, str(Path(__file__).resolve().parent))


# the scratch PostgreSQL databases of the other benchmarks
from _machine import machine, write_section
from catalog_queries import T0, populate
from ingest_rate import _drop_pg, _fresh_pg


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


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (0 if it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _workers(pid: int) -> list[int]:
    """The server's worker processes: its children (Linux /proc)."""
    children = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(c) for c in children.read_text().split()] if children.exists() else []


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))]


KINDS = ("list", "range", "acquisition", "patient")
PATHS = 5_000  # request paths drawn up front; wrk's threads pick among them at random
SEED = 3

# wrk script; the Python side prepends `paths = {...}`, the token header and RESULT.
# Each thread formats every request once in init(); request() then only picks one.
_WRK_LUA = r"""
local counter = 0
function setup(thread)
  counter = counter + 1
  thread:set("tid", counter)
end

local requests_ = {}
function init(args)
  math.randomseed(SEED + (tid or 0))
  for i, path in ipairs(paths) do
    requests_[i] = wrk.format("GET", path)
  end
end

function request()
  return requests_[math.random(#requests_)]
end

function done(summary, latency, requests)
  local e = summary.errors
  local f = assert(io.open(RESULT, "w"))
  f:write(string.format(
    '{"requests": %d, "duration_us": %d, "bytes": %d, "status": %d, "connect": %d, ' ..
    '"read": %d, "write": %d, "timeout": %d, "p50": %f, "p90": %f, "p95": %f, ' ..
    '"p99": %f, "p999": %f, "max": %f, "mean": %f}\n',
    summary.requests, summary.duration, summary.bytes, e.status, e.connect, e.read,
    e.write, e.timeout, latency:percentile(50), latency:percentile(90),
    latency:percentile(95), latency:percentile(99), latency:percentile(99.9),
    latency.max, latency.mean))
  f:close()
end
"""


def _paths(mix: str, uids: list[str],
           patients: list[str]) -> tuple[list[str], dict[str, int], dict[str, str]]:
    """Draw the request paths (seeded): the paths, how many of each kind, one of each kind."""
    rng = random.Random(SEED)
    paths: list[str] = []
    first: dict[str, str] = {}
    composition = dict.fromkeys(KINDS if mix == "all" else (mix,), 0)
    for _ in range(PATHS):
        kind = rng.choice(KINDS) if mix == "all" else mix
        if kind == "list":
            query = {"patient": rng.choice(patients), "limit": 100}
            path = "/acquisitions?" + urlencode(query)
        elif kind == "range":
            # with its zone: the API refuses a time without one
            start = T0 + dt.timedelta(days=rng.uniform(0, 5 * 365 - 30))
            query = {"since": start.isoformat(timespec="seconds"),
                     "until": (start + dt.timedelta(days=30)).isoformat(timespec="seconds")}
            path = "/acquisitions?" + urlencode(query)
        elif kind == "acquisition":
            path = f"/acquisitions/{quote(rng.choice(uids))}"
        else:
            path = f"/patients/{quote(rng.choice(patients))}"
        paths.append(path)
        composition[kind] += 1
        first.setdefault(kind, path)
    return paths, composition, first


def _lua_string(value: str) -> str:
    if not value.isascii() or any(c in value for c in '"\\\n\r'):
        raise ValueError(f"not a plain Lua string: {value!r}")
    return f'"{value}"'


def _probe(url: str, token: str, paths: list[str]) -> list[str]:
    """GET ``paths`` one by one; describe (up to 5 of) those that did not answer 200."""
    bad: list[str] = []
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"},
                      timeout=120) as client:
        for path in paths:
            try:
                response = client.get(path)
                if response.status_code != 200:
                    bad.append(f"{path} -> {response.status_code} {response.text[:200]}")
            except httpx.HTTPError as exc:
                bad.append(f"{path} -> {type(exc).__name__}")
            if len(bad) >= 5:
                break
    return bad


def _readers(url: str, token: str, args: argparse.Namespace, paths: list[str],
             tmp: Path) -> dict[str, object]:
    """Run wrk (closed loop, ``--clients`` connections) over ``paths``; its summary."""
    result = tmp / "wrk.json"
    script = tmp / "api_load.lua"
    script.write_text(
        "paths = {\n" + ",\n".join(_lua_string(p) for p in paths) + "\n}\n"
        f'wrk.headers["Authorization"] = {_lua_string("Bearer " + token)}\n'
        f"SEED = {SEED}\nRESULT = {_lua_string(str(result))}\n" + _WRK_LUA)
    seconds = max(1, round(args.seconds))
    cmd = ["wrk", "-t", "2", "-c", str(args.clients), "-d", f"{seconds}s", "--timeout", "30s",
           "--latency", "-s", str(script), url]
    # wrk is the only child that ends in here (the server is still running), so the
    # children's rusage grows by exactly wrk's CPU time
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds + 120)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    wrk_cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    print(done.stdout, done.stderr, sep="", flush=True)
    if done.returncode != 0 or not result.exists():
        raise RuntimeError(f"wrk failed ({done.returncode}): {done.stderr or done.stdout}")
    out = json.loads(result.read_text())
    duration = out["duration_us"] / 1e6
    socket = {k: out[k] for k in ("connect", "read", "write", "timeout") if out[k]}
    return {
        "requests": out["requests"], "duration": duration,
        "rps": out["requests"] / duration if duration else 0.0,
        "status_errors": out["status"], "socket_errors": socket,
        "errors": out["status"] + sum(socket.values()),
        "wrk_cpu": wrk_cpu / duration if duration else 0.0,  # cores used by wrk
        **{q: out[q] / 1000 for q in ("p50", "p90", "p95", "p99", "p999", "max", "mean")},
    }


async def _stations(url: str, tokens: list[str], uploads: int,
                    patients: list[str]) -> tuple[dict[str, str], list[float], int, int]:
    stored: dict[str, str] = {}  # uid -> sha256 of the frame sent
    latencies: list[float] = []
    errors = 0
    replays = 0  # retries (same Idempotency-Key) answered 200 with the first attempt's uid

    async def station(k: int, token: str) -> None:
        nonlocal errors, replays
        rng = np.random.default_rng(1000 + k)
        async with httpx.AsyncClient(base_url=url, timeout=300,
                                     headers={"Authorization": f"Bearer {token}"}) as client:
            for i in range(uploads):
                image = rng.integers(0, 256, (604, 576), dtype=np.uint8)
                buffer = io.BytesIO()
                np.save(buffer, image, allow_pickle=False)
                request = {"files": [("files", (f"s{k}-{i}.npy", buffer.getvalue()))],
                           "data": {"patient": patients[(k * uploads + i) % len(patients)]},
                           "headers": {"Idempotency-Key": f"station-{k}/{i}"}}
                t = time.perf_counter()
                try:
                    response = await client.post("/acquisitions", **request)
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
                if i % 5 == 4:
                    # as a station does that lost the answer: the same upload, the same key
                    try:
                        retry = await client.post("/acquisitions", **request)
                    except httpx.HTTPError:
                        errors += 1
                        continue
                    if retry.status_code == 200 and retry.json()["uid"] == uid:
                        replays += 1
                    else:
                        errors += 1

    await asyncio.gather(*(station(k, t) for k, t in enumerate(tokens)))
    return stored, latencies, errors, replays


def run(backend: str, args: argparse.Namespace) -> dict[str, object]:
    if args.dir:
        Path(args.dir).mkdir(parents=True, exist_ok=True)
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
            paths, composition, first = _paths(args.mix, uids, patients)
            server_log = Path(tmp) / "server.log"
            server, base = _start(settings, args.workers, server_log)
            try:
                # one request of each kind first: a mix the server refuses outright (a
                # malformed path, say) is reported as such, not measured as a rate
                bad = _probe(base, reader, list(first.values()))
                if bad:
                    print("reader paths refused:", *bad, sep="\n  ", flush=True)
                workers = _workers(server.pid)
                before = sum(_cpu_seconds(w) for w in workers)
                readers = _readers(base, reader, args, paths, Path(tmp))
                # the server's CPU per request: less sensitive than latency to how the
                # load happened to be spread, more to how fast the machine was that minute
                readers["server_ms_per_request"] = 1000 * (
                    sum(_cpu_seconds(w) for w in workers) - before) / max(readers["requests"], 1)
                if readers["status_errors"]:
                    bad = _probe(base, reader, paths[:200])
                    print("reader failures (sample, after the run):", *bad, sep="\n  ",
                          flush=True)
                t = time.perf_counter()
                stored, up_lat, up_errors, replays = asyncio.run(
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
        "backend": backend, "fill": fill, **readers, "composition": composition,
        "uploads_expected": expected,
        "uploads_ok": len(stored), "upload_errors": up_errors, "replays": replays,
        "retries": args.stations * (args.uploads // 5),
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


def _ms(value: float) -> str:
    return f"{value:.1f}" if value < 10 else f"{value:,.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--acquisitions", type=int, default=100_000)
    parser.add_argument("--patients", type=int, default=5_000)
    parser.add_argument("--clients", type=int, default=50, help="wrk connections")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--mix", choices=("all", *KINDS), default="all",
                        help="read requests of one kind only (default: all four)")
    parser.add_argument("--stations", type=int, default=20)
    parser.add_argument("--uploads", type=int, default=10, help="acquisitions per station")
    parser.add_argument("--workers", type=int, default=2, help="uvicorn worker processes")
    parser.add_argument("--postgres", default=None,
                        help="also run on PostgreSQL (admin URL of a server)")
    parser.add_argument("--dir", default=None, help="folder for the temporary archive")
    parser.add_argument("--repeat", type=int, default=1,
                        help="runs of each catalogue, interleaved (the VM's speed drifts)")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args()
    if shutil.which("wrk") is None:
        sys.exit("api_load: wrk not found; install wrk: apt-get install wrk")
    if args.clients < 2:
        parser.error("--clients must be at least 2 (wrk runs 2 threads)")
    load = os.getloadavg()[0]
    results = []
    for n in range(1, args.repeat + 1):
        for backend in ("sqlite", *(("postgresql",) if args.postgres else ())):
            r = run(backend, args)
            if args.repeat > 1:
                r["backend"] = f"{backend} ({n})"
            print(r, flush=True)
            results.append(r)

    def errors(r: dict[str, object]) -> str:
        parts = [f"{r['status_errors']} HTTP"] if r["status_errors"] else []
        parts += [f"{v} {k}" for k, v in r["socket_errors"].items()]  # type: ignore[union-attr]
        return f"{r['errors']}" + (f" ({', '.join(parts)})" if parts else "")

    rows_read = "\n".join(
        f"| {r['backend']} | {r['requests']:,} | {r['rps']:.0f} | {_ms(r['p50'])} | "
        f"{_ms(r['p90'])} | {_ms(r['p95'])} | {_ms(r['p99'])} | {_ms(r['p999'])} | "
        f"{_ms(r['max'])} | {r['server_ms_per_request']:.2f} | {errors(r)} |"
        for r in results)
    rows_up = "\n".join(
        f"| {r['backend']} | {r['uploads_ok']} / {r['uploads_expected']} | "
        f"{r['replays']} / {r['retries']} | {r['upload_errors']} "
        f"| {r['upload_wall']:.1f} s ({r['uploads_ok'] / r['upload_wall']:.1f}/s) | "
        f"{r['upload_p50']:.0f} / {r['upload_p99']:.0f} | "
        f"{'yes' if r['stored_once'] and r['checksums_match'] else 'NO'} | "
        f"{'clean' if r['verify_ok'] else 'PROBLEMS'} ({r['verified_frames']:,} frames, "
        f"{r['verify_s']:.1f} s) |" for r in results)
    composition = results[0]["composition"]
    described = {
        "list": "one patient's acquisitions (up to 100)",
        "range": "a 30-day range (first page of 100)",
        "acquisition": "one acquisition's metadata",
        "patient": "one patient",
    }
    mix = "; ".join(f"{described[k]}: {v:,}" for k, v in composition.items())  # type: ignore[union-attr]
    body = (
        f"Machine: {machine()}. Load average before the run: {load:.1f} (the machine was "
        "shared with other jobs; server and load generator ran on the same cores).\n\n"
        f"Server: `rasterserver serve --workers {args.workers}` on loopback; every request "
        "authenticated (token digest look-up; on PostgreSQL from the token cache that "
        "LISTEN/NOTIFY empties) and audited (one append-only event per request, linked to "
        "every patient it touched, committed before the response starts; concurrent "
        "requests share the commit; the by-patient audit index is filled every 10 s by the "
        "background indexer, whose work is part of the load).\n\n"
        f"**Readers**: {args.acquisitions:,} acquisitions of {args.patients:,} patients "
        "catalogued. The load comes from `wrk` (a C program, in its own process on the same "
        "2 cores as the server; on average it used "
        + ", ".join(f"{r['wrk_cpu']:.2f} of a core on {r['backend']}" for r in results)
        + f"): 2 threads, {args.clients} keep-alive connections (the server closes each "
        "after 5 s of use and wrk reconnects), closed "
        f"loop (each connection sends its next request when the last is answered) for "
        f"{args.seconds:.0f} s, each request drawn at random from {PATHS:,} paths "
        f"pre-generated with a fixed seed ({mix}). Latency in ms, as wrk measures it; "
        "errors are HTTP error statuses plus socket errors (connect, read, write, timeout "
        "after 30 s). Server CPU: user + system time of the worker processes over the run, "
        "per request answered (includes the audit writer and indexer)."
        + (f" {args.repeat} runs of each catalogue, interleaved, a fresh archive each: the "
           "VM's speed drifts by ±20–30 % over minutes, which the CPU column shows."
           if args.repeat > 1 else "") + "\n\n"
        "| catalogue | requests | req/s | p50 | p90 | p95 | p99 | p99.9 | max | server CPU "
        "ms/request | errors |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n" + rows_read + "\n\n"
        f"**Stations**: {args.stations} concurrent station accounts, {args.uploads} uploads "
        "each of one 604x576 uint8 frame (NPY, multipart; asyncio + httpx clients), each with "
        "an `Idempotency-Key`; every fifth upload is sent a second time with the same key, "
        "as a station does that lost the answer (retried: answered 200 with the first "
        "attempt's acquisition). Checked "
        "afterwards: every upload in the catalogue exactly once with the SHA-256 of the frame "
        "sent, and `Archive.verify()` re-hashing every stored frame (clean = no problem with "
        "an upload and no orphaned, temporary or stray file; the bulk-inserted rows have no "
        "files by design and are left out).\n\n"
        "| catalogue | stored | retried | errors | wall time | latency p50 / p99 (ms) | once, "
        "checksums equal | verify |\n|---|---:|---:|---:|---:|---:|---|---|\n" + rows_up + "\n\n"
        "Reading the numbers: each read costs a token look-up, one catalogue query (the page "
        "joined to its frames and patients), JSON for up to 100 acquisitions, and its share "
        "of a group-committed audit transaction (one event and up to 100 patient links, "
        "fsynced before the response starts). On PostgreSQL the database server's own "
        "processes also run on the same two cores. "
        f"The server's {args.workers} workers share the two cores with wrk (its share "
        "above) and with other jobs, so the throughput is "
        "CPU-bound and the tail latencies are mostly queueing in a closed loop of "
        f"{args.clients} connections; on a dedicated machine expect more.\n\n"
        "Script: `benchmarks/api_load.py` (`--mix list|range|acquisition|patient` runs one "
        "kind of read only)."
    )
    if not args.no_write:
        write_section("HTTP API", body)
    print(body)


if __name__ == "__main__":
    main()
