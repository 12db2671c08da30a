"""Benchmark the simulator's renderer: one frame of a ~100k-triangle smooth bumpy surface.

Renders the seed's 604 x 576 portrait frame with 3 x 3 supersampling (and a 2048 x 2448
frame) of a height field that does not depend on the back model, and reports the median
wall time of several runs with its split (ray building, ray casting, shadow rays, shading,
blur + noise, ground truth). The first run of a camera also builds its (cached) ray table;
it is reported separately as "cold".

Usage::

    .venv/bin/python benchmarks/render_speed.py [--runs 7] [--large-runs 2] [--write]

``--write`` replaces the "Simulator rendering" section of BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import machine, write_section

from rasterserver.optics import default_station
from rasterserver.simulator.render import RenderSettings, render
from rasterserver.simulator.scene import Scene, SceneObject

PHASES = (
    "subsamples",
    "rays",
    "ray_casting",
    "shadow_rays",
    "shading",
    "blur_noise",
    "pixel_truth",
    "line_rows",
    "total",
)


def bumpy_surface(n: int = 224, half_size: float = 450.0) -> o3d.geometry.TriangleMesh:
    """A smooth height field ``z(x, y)`` (+-30 mm bumps) with ``2 (n-1)**2`` triangles."""
    s = np.linspace(-half_size, half_size, n)
    gx, gy = np.meshgrid(s, s)
    gz = (
        25.0 * np.sin(gx / 70.0) * np.cos(gy / 90.0)
        + 8.0 * np.cos((gx + 2 * gy) / 35.0)
        - 40.0 * np.exp(-(gx**2 + gy**2) / 300.0**2)
    )
    vertices = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(tris)
    )
    mesh.compute_vertex_normals()
    return mesh


def measure(
    scene: Scene, width: int, height: int, runs: int, settings: RenderSettings
) -> tuple[float, dict[str, float], float, float]:
    """Cold time, median phase times of ``runs`` warm renders, best total, median CPU time."""
    station = default_station(width, height)
    t0 = time.perf_counter()
    render(scene, station, settings=settings, seed=0)
    cold = time.perf_counter() - t0
    phases: dict[str, list[float]] = {k: [] for k in PHASES}
    cpu: list[float] = []
    for i in range(runs):
        c0 = time.process_time()
        r = render(scene, station, settings=settings, seed=i + 1)
        cpu.append(time.process_time() - c0)
        for k in PHASES:
            phases[k].append(r.timings.get(k, 0.0))
    medians = {k: statistics.median(v) for k, v in phases.items()}
    return cold, medians, min(phases["total"]), statistics.median(cpu)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--large-runs", type=int, default=2)
    parser.add_argument("--write", action="store_true", help="update BENCHMARKS.md")
    args = parser.parse_args()

    load_start = os.getloadavg()[0]
    mesh = bumpy_surface()
    n_tri = len(mesh.triangles)
    scene = Scene([SceneObject("bumps", mesh, 0.8)])
    settings = RenderSettings()
    rows = []
    for label, (w, h), runs, s in [
        ("576 x 604, 3 x 3", (576, 604), args.runs, settings),
        (
            "576 x 604, 3 x 3, no line_rows",
            (576, 604),
            args.runs,
            settings.replace(line_rows=False),
        ),
        ("2048 x 2448, 3 x 3", (2048, 2448), args.large_runs, settings),
    ]:
        if runs <= 0:
            continue
        cold, med, best, cpu = measure(scene, w, h, runs, s)
        rows.append((label, runs, cold, med, best, cpu))
        print(label, f"cold {cold:.3f} s", {k: round(v, 3) for k, v in med.items()}, flush=True)

    load_end = os.getloadavg()[0]
    head = "| frame | runs | median total (s) | best (s) | cold (s) | CPU (s) | "
    head += " | ".join(PHASES[:-1])
    lines = [head + " |", "|" + "---|" * (6 + len(PHASES) - 1)]
    for label, runs, cold, med, best, cpu in rows:
        cells = [label, str(runs), f"**{med['total']:.3f}**", f"{best:.3f}", f"{cold:.2f}"]
        cells.append(f"{cpu:.2f}")
        cells += [f"{med[k]:.3f}" for k in PHASES[:-1]]
        lines.append("| " + " | ".join(cells) + " |")
    body = "\n".join(
        [
            f"`benchmarks/render_speed.py`: {machine()}.",
            "",
            f"Scene: one smooth bumpy height field of {n_tri} triangles (vertex-normal "
            "shading) filling the field of view; default station (camera k1 = -0.05, "
            "projector k1 = -0.01) and `RenderSettings()` (3 x 3 supersampling, shadow rays, "
            "PSF, shot + read noise, 8 bit). Times are wall-clock medians in seconds; *cold* "
            "is the first render of a camera, which also builds its cached ray table; CPU is "
            "the process CPU time (ray casting uses both cores). `pixel_truth` and "
            "`line_rows` are the ground truth (per-pixel maps; exact line rows per column). "
            "`subsamples` is the wall time of the sub-sample pass, whose parts (`rays`, "
            "`ray_casting`, `shadow_rays`, `shading`) are summed over its worker threads. "
            f"The machine was shared with other jobs: 1-min load average {load_start:.1f} "
            f"before and {load_end:.1f} after the runs (2 cores), so medians are "
            "pessimistic; *best* is the fastest run. Wall time close to CPU time means the "
            "process effectively had one core.",
            "",
            *lines,
        ]
    )
    print(body)
    if args.write:
        write_section("Simulator rendering", body)


if __name__ == "__main__":
    main()
