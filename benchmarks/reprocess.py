"""Reprocessing throughput, end to end (issue 16): read, compute to mesh, write, commit.

An archive of N simulated 604x576 acquisitions (SQLite catalogue) is built once and cached
under ``--cache`` (default ``/tmp/rasterserver-reprocess``); before each measurement its
derived files, stage results, pipeline runs and jobs are removed, so every run computes
everything. Each measurement is one catalogue job (``Selection(all=True)``, target mesh),
as ``rasterserver process --all`` runs it:

* ``in-process``: the coordinator computes and writes the files itself;
* ``dask-1``, ``dask-2``: a ``LocalCluster`` of 1 or 2 worker processes (one thread each),
  started before the clock (its start is reported apart), the workers reading frames and
  writing files, the coordinator only planning and committing rows.

Reported per run: acquisitions per second, wall and CPU time per acquisition (coordinator and
workers, from ``/proc``: CPU time depends less on the machine's load than wall time), the
coordinator's CPU per acquisition, and peak resident memory of the coordinator and the
workers. ``--sizes`` runs the in-process engine at several N to show that memory does not
grow with N.

Run: ``nice .venv/bin/python benchmarks/reprocess.py [N] [--sizes 250,500] [--write]``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import datetime as dt  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import psutil  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import geometry_truth as gt  # noqa: E402
from _machine import add_write_options, machine, subsection_heading, write_subsection  # noqa: E402
from sqlalchemy import delete, func, select, update  # noqa: E402

from rasterserver.archive import Archive, FrameSource  # noqa: E402
from rasterserver.catalog.job_models import ProcessingJob, ProcessingTask  # noqa: E402
from rasterserver.catalog.models import (  # noqa: E402
    Acquisition,
    PipelineRun,
    StageResult,
    StageResultInput,
)
from rasterserver.config import Settings, sqlite_url  # noqa: E402
from rasterserver.jobs import dask_client  # noqa: E402
from rasterserver.processing_jobs import Selection, create_job, run_job  # noqa: E402

TITLE = "Reprocessing throughput"
HEADER = (
    "| engine | acquisitions | s | acquisitions/s | wall ms/acq | CPU ms/acq | "
    "coordinator CPU ms/acq | loop CPU ms/acq | coordinator peak RSS MB | "
    "worker peak RSS MB |\n"
    "|---|---|---|---|---|---|---|---|---|---|"
)


def settings_for(root: Path) -> Settings:
    return Settings(archive=root / "archive", database_url=sqlite_url(root / "archive"))


def build(root: Path, count: int) -> Settings:
    """The cached archive of ``count`` acquisitions (built the first time)."""
    settings = settings_for(root)
    done = root / f"built-{count}"
    if done.exists():
        return settings
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    t0 = time.perf_counter()
    image = gt.rendering("back").image
    archive, _ = gt.archive_with_frames(settings, {})
    start = dt.datetime(2025, 3, 1, tzinfo=dt.UTC)
    with archive:
        for k in range(count):
            archive.ingest(
                [FrameSource(image, role="raster", name=f"b{k}.npy")],
                patient="P1",
                station=gt.STATION_NAME,
                acquired_at=start + dt.timedelta(seconds=k),
            )
            if k and k % 500 == 0:
                print(f"  built {k}/{count}", file=sys.stderr, flush=True)
    done.write_text(f"{time.perf_counter() - t0:.0f} s\n")
    return settings


def reset(settings: Settings) -> None:
    """Forget every result: derived files and their rows, runs, jobs."""
    shutil.rmtree(Path(settings.archive) / "derived", ignore_errors=True)
    with Archive(settings) as archive, archive.session() as s:
        s.execute(update(StageResult).values(parent_id=None))
        for table in (StageResultInput, StageResult, PipelineRun, ProcessingTask, ProcessingJob):
            s.execute(delete(table))


@dataclass
class Run:
    engine: str
    count: int
    seconds: float
    coordinator_cpu: float
    worker_cpu: float
    coordinator_rss: float
    worker_rss: float
    start_s: float = 0.0
    loop_cpu: float = 0.0

    @property
    def rate(self) -> float:
        return self.count / self.seconds

    def row(self) -> str:
        per = 1000 / self.count
        return (
            f"| {self.engine} | {self.count} | {self.seconds:.1f} | {self.rate:.1f} | "
            f"{self.seconds * per:.0f} | {(self.coordinator_cpu + self.worker_cpu) * per:.0f} | "
            f"{self.coordinator_cpu * per:.1f} | {self.loop_cpu * per:.1f} | "
            f"{self.coordinator_rss:.0f} | "
            f"{self.worker_rss:.0f} |"
        )


def _cpu(process: psutil.Process) -> float:
    times = process.cpu_times()
    return times.user + times.system


def _peak_rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def _warm() -> None:
    from rasterserver.registry import get_registry

    registry = get_registry()
    for kind in registry.stage_kinds():
        registry.default_for(kind)


def measure(settings: Settings, count: int, workers: int) -> Run:
    """One job over every acquisition: in-process (``workers`` 0) or on a local cluster."""
    reset(settings)
    me = psutil.Process()
    with Archive(settings) as archive:
        with archive.session() as s:
            total = s.scalar(select(func.count()).select_from(Acquisition))
        assert total == count, (total, count)
        job, _ = create_job(archive, Selection(all=True), targets=["mesh"])
        if workers == 0:
            c0 = _cpu(me)
            l0 = time.thread_time()
            t0 = time.perf_counter()
            status = run_job(archive, job.id, dask=False)
            seconds = time.perf_counter() - t0
            run = Run(
                "in-process",
                count,
                seconds,
                _cpu(me) - c0,
                0.0,
                _peak_rss_mb(me.pid),
                0.0,
                loop_cpu=time.thread_time() - l0,
            )
        else:
            s0 = time.perf_counter()
            with dask_client(n_workers=workers) as client:
                # the workers import the plugins before the clock, as a long-lived cluster has
                client.run(_warm)
                start_s = time.perf_counter() - s0
                pids = [p for p in me.children(recursive=True)]
                w0 = sum(_cpu(p) for p in pids)
                c0 = _cpu(me)
                l0 = time.thread_time()
                t0 = time.perf_counter()
                status = run_job(archive, job.id, client=client)
                seconds = time.perf_counter() - t0
                loop = time.thread_time() - l0
                coordinator = _cpu(me) - c0
                worker = sum(_cpu(p) for p in pids) - w0
                worker_rss = max((_peak_rss_mb(p.pid) for p in pids), default=0.0)
            run = Run(
                f"local cluster, {workers} worker(s)",
                count,
                seconds,
                coordinator,
                worker,
                _peak_rss_mb(me.pid),
                worker_rss,
                start_s,
                loop,
            )
        assert status.job.state == "done" and status.job.done == count, status.to_dict()
    print(run.row(), file=sys.stderr, flush=True)
    return run


def _child(cache: Path, count: int, workers: int) -> Run:
    out = subprocess.run(
        [sys.executable, __file__, str(count), "--cache", str(cache), "--one", str(workers)],
        check=True,
        stdout=subprocess.PIPE,
        text=True,
    ).stdout
    return Run(**json.loads(out.strip().splitlines()[-1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("count", type=int, nargs="?", default=1000)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/rasterserver-reprocess"))
    parser.add_argument("--sizes", default="", help="in-process runs at these N too (memory)")
    parser.add_argument("--engines", default="0,1,2", help="0 in-process, k: k dask workers")
    add_write_options(parser)
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.one is not None:
        settings = build(args.cache / f"n{args.count}", args.count)
        if args.one >= 0:  # -1: build only
            print(json.dumps(asdict(measure(settings, args.count, args.one))))
        return
    load_before = os.getloadavg()
    print(HEADER)
    runs: list[Run] = []
    todo = [(size, 0) for size in [int(x) for x in args.sizes.split(",") if x]]
    todo += [(args.count, int(x)) for x in args.engines.split(",") if x]
    for size in sorted({size for size, _w in todo}):
        subprocess.run(
            [sys.executable, __file__, str(size), "--cache", str(args.cache), "--one", "-1"],
            check=True,
        )
    for size, workers in todo:
        # each in a fresh process: peak memory is that of one job, not of the ones before
        runs.append(_child(args.cache, size, workers))
    load_after = os.getloadavg()
    table = "\n".join(r.row() for r in runs)
    by = {r.engine: r for r in runs if r.count == args.count}
    one = by.get("local cluster, 1 worker(s)")
    two = by.get("local cluster, 2 worker(s)")
    inproc = by.get("in-process")
    lines = []
    if one and two:
        lines.append(f"1 → 2 workers: {two.rate / one.rate:.2f}× the acquisitions per second.")
    if inproc and two:
        lines.append(
            f"Local cluster (2 workers) against in-process: "
            f"{two.rate / inproc.rate:.2f}× the acquisitions per second."
        )
    if two and two.loop_cpu:
        loop = 1000 * two.loop_cpu / two.count
        # a worker's CPU per acquisition it computes: the workers' CPU over the acquisitions
        work = 1000 * two.worker_cpu / two.count
        lines.append(
            f"Cluster estimate: the coordinator's loop (planning, committing rows; its main "
            f"thread) spends {loop:.1f} ms of CPU per acquisition, a worker {work:.0f} ms; one "
            f"coordinator saturates at about {1000 / loop:.0f} acquisitions/s, i.e. about "
            f"{work / loop:.0f} single-threaded workers."
        )
        derived = Path(settings_for(args.cache / f"n{args.count}").archive) / "derived"
        written = sum(f.stat().st_size for f in derived.rglob("*.h5")) / args.count / 1e6
        per_worker = written * 1000 / work  # MB/s one busy worker writes
        lines.append(
            f"Storage: {written:.1f} MB of derived files per acquisition, ~{per_worker:.0f} "
            f"MB/s per busy worker: shared storage of 1.1 GB/s (10 GbE) serves about "
            f"{1100 / per_worker:.0f} workers."
        )
    sizes = f" --sizes {args.sizes}" if args.sizes else ""
    starts = ", ".join(f"{r.engine}: {r.start_s:.1f} s" for r in runs if r.start_s)
    load = f"load average {load_before[0]:.1f} before, {load_after[0]:.1f} after"
    body = f"""{machine()}; {load} (the machine is shared with other helpers: wall times are
slow and noisy, CPU times less so). `nice benchmarks/reprocess.py {args.count}{sizes}`: one
catalogue job (target mesh) over N cached simulated 604×576 acquisitions on SQLite, every
stage computed (results removed before each run), each job in a fresh process. Cluster start
and plugin import on the workers (not in the times): {starts or "-"}.

{HEADER}
{table}

{chr(10).join(lines)}"""
    print(body)
    if args.write:
        write_subsection(TITLE, subsection_heading(args.heading, __file__), body)


if __name__ == "__main__":
    main()
