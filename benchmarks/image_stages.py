"""Image-processing stages 1-4: peak accuracy against the truth, peak counts, stage timings.

* peak location error (px): detected peak rows against the simulator's exact line-centre
  rows, at the default noise, for the preset backs and a flat wall (rms over the peaks
  matched within 1.5 px; also the median absolute error and the 99th percentile);
* the number of peaks of a medium back (the seed reports ~25,000 at its geometry);
* per-stage time, median (and best) of ``--repeat`` runs on one thread, for the seed's
  604 x 576 frame and a 2448 x 2048 (5 MP) portrait frame, with the share of each step of
  the peak detector and the line search (profiled by statement).

Usage::

    python benchmarks/image_stages.py [--repeat 30] [--no-large]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

from rasterserver_plugins.line_numbering import CodeWindowNumbering  # noqa: E402
from rasterserver_plugins.line_search import HierarchicalLineSearch  # noqa: E402
from rasterserver_plugins.line_sequence import HierarchicalLineOrder  # noqa: E402
from rasterserver_plugins.peak_detection import FirstMomentPeaks  # noqa: E402

from rasterserver.optics import default_station  # noqa: E402
from rasterserver.records import Image  # noqa: E402
from rasterserver.simulator.back import make_back, preset  # noqa: E402
from rasterserver.simulator.render import RenderSettings, render  # noqa: E402
from rasterserver.stage import StageContext, run_stage  # noqa: E402


def machine() -> dict[str, Any]:
    """CPU model, cores, Python and numpy versions."""
    cpu = platform.processor() or "?"
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        for line in out.splitlines():
            if line.startswith("Model name"):
                cpu = line.split(":", 1)[1].strip()
    except OSError:
        pass
    return {
        "cpu": cpu,
        "nproc": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "date": time.strftime("%Y-%m-%d"),
    }


def truth_rows(col: np.ndarray, row: np.ndarray, lr: Any, tol: float = 1.5) -> np.ndarray:
    """Exact row of the line centre nearest to each peak in its column (NaN: none near)."""
    o = np.lexsort((lr.row, lr.column))
    kg = lr.column[o].astype(np.int64) * 1e5 + lr.row[o]
    gr = lr.row[o]
    kp = col.astype(np.int64) * 1e5 + row
    j = np.clip(np.searchsorted(kg, kp), 1, kg.size - 1)
    e0, e1 = np.abs(kg[j - 1] - kp), np.abs(kg[j] - kp)
    jj = np.where(e0 < e1, j - 1, j)
    return np.where(np.minimum(e0, e1) < tol, gr[jj], np.nan)


def scaled_params(scale: float) -> dict[str, dict[str, Any]]:
    """Stage parameters for a sensor with ``scale`` times the seed's pixels per mm.

    Widths in pixels grow with the scale, slopes in grey values per pixel shrink, and the
    lengths counted in columns (seeds, neighbourhoods) grow, so that each criterion means
    the same on the back. Row steps between adjacent columns are slopes and do not change.
    """
    if scale <= 1.0:
        return {"peaks": {}, "lines": {}, "order": {}, "numbers": {}}
    k = float(scale)
    return {
        "peaks": {"max_width": round(25 * k), "min_slope": 2.5 / k},
        "lines": {
            "corner": 1.5 / k**0.5,
            "dip_window": round(20 * k),
            "smooth": round(2 * k),
            "min_seed": round(8 * k),
            "min_length": round(3 * k),
        },
        "order": {"min_overlap": round(3 * k), "min_link": round(6 * k)},
        "numbers": {"min_columns": round(5 * k)},
    }


def accuracy(settings: RenderSettings, scenes: dict[str, Any]) -> dict[str, Any]:
    """Peak errors per scene at ``settings``."""
    station = default_station()
    out = {}
    for name, scene in scenes.items():
        r = render(scene, station, settings=settings, seed=11)
        peaks = run_stage(FirstMomentPeaks, Image(r.image))
        exact = truth_rows(peaks.col, peaks.row, r.line_rows)
        ok = ~np.isnan(exact)
        err = peaks.row[ok] - exact[ok]
        out[name] = {
            "peaks": int(peaks.n_peaks),
            "true_centres": len(r.line_rows),
            "matched": int(ok.sum()),
            "rms_px": round(float(np.sqrt(np.mean(err**2))), 4),
            "bias_px": round(float(np.mean(err)), 4),
            "median_abs_px": round(float(np.median(np.abs(err))), 4),
            "p99_abs_px": round(float(np.percentile(np.abs(err), 99)), 4),
        }
    return out


def numbering_check(result: Any, lr: Any, tol: float) -> dict[str, Any]:
    """Lines numbered, wrongly numbered (majority truth differs), and peak coverage."""
    from numbering_backs import _truth_numbers  # the sibling benchmark's truth matching

    number = _truth_numbers(result.col, result.row, lr, tol=tol, resolve=2.0 * tol)
    wrong = numbered = 0
    for line in range(result.line_order.size):
        truth = number[(result.line_id == line) & (number >= 0)]
        if truth.size and result.line_number[line] >= 0:
            numbered += 1
            wrong += int(np.bincount(truth).argmax() != result.line_number[line])
    on = number >= 0
    return {
        "lines": int(result.line_order.size),
        "numbered": numbered,
        "wrong": wrong,
        "peak_coverage": round(float(np.mean(result.number[on] == number[on])), 4),
    }


def timings(image: np.ndarray, repeat: int, scale: float) -> dict[str, Any]:
    """Median and best ms per stage over ``repeat`` runs; the last result under "result"."""
    ctx = StageContext(raster=default_station().raster_definition)
    sp = scaled_params(scale)
    stages = [
        (FirstMomentPeaks, sp["peaks"], None),
        (HierarchicalLineSearch, sp["lines"], None),
        (HierarchicalLineOrder, sp["order"], None),
        (CodeWindowNumbering, sp["numbers"], ctx),
    ]
    runs = []
    result: Any = None
    for _ in range(repeat):
        data: Any = Image(image)
        row = []
        for cls, params, context in stages:
            t = time.perf_counter()
            data = run_stage(cls, data, params, context)
            row.append(time.perf_counter() - t)
        runs.append(row)
        result = data
    arr = np.array(runs) * 1e3
    names = ["peaks", "lines", "order", "numbers"]
    return {
        "median_ms": dict(zip(names, np.median(arr, axis=0).round(2).tolist(), strict=True)),
        "best_ms": dict(zip(names, arr.min(axis=0).round(2).tolist(), strict=True)),
        "total_median_ms": round(float(np.median(arr.sum(axis=1))), 2),
        "total_best_ms": round(float(arr.sum(axis=1).min()), 2),
        "peaks": int(result.n_peaks),
        "lines": int(result.line_order.size),
        "numbered_share": round(float(np.mean(result.number >= 0)), 4) if result.n_peaks else 0.0,
        "reason": result.reason,
        "result": result,
    }


def profile(
    func: Any, args: tuple[Any, ...], kwargs: dict[str, Any], repeat: int
) -> list[tuple[str, float]]:
    """Best time per top-level statement of ``func`` (ms), largest first."""
    import ast
    import inspect
    import textwrap

    src = textwrap.dedent(inspect.getsource(func))
    tree = ast.parse(src)
    fn = tree.body[0]
    assert isinstance(fn, ast.FunctionDef)
    body = []
    for stmt in fn.body:
        body.append(stmt)
        if not isinstance(stmt, ast.Return):
            body.append(ast.parse(f"_T.append(({stmt.lineno}, _time.perf_counter()))").body[0])
    fn.body = body
    ns = dict(sys.modules[func.__module__].__dict__)
    marks: list[tuple[int, float]] = []
    ns["_T"], ns["_time"] = marks, time
    exec(compile(ast.fix_missing_locations(tree), func.__module__, "exec"), ns)
    best: dict[int, float] = {}
    lines = src.splitlines()
    for _ in range(repeat):
        marks.clear()
        t0 = time.perf_counter()
        ns[fn.name](*args, **kwargs)
        prev = t0
        seen: dict[int, float] = {}
        for lineno, t in marks:
            seen[lineno] = seen.get(lineno, 0.0) + t - prev
            prev = t
        for k, v in seen.items():
            best[k] = min(best.get(k, np.inf), v)
    ranked = sorted(best.items(), key=lambda kv: -kv[1])
    return [(lines[k - 1].strip()[:80], round(v * 1e3, 3)) for k, v in ranked[:8]]


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--no-large", action="store_true", help="skip the 2448 x 2048 frame")
    args = ap.parse_args(argv)
    report: dict[str, Any] = {"machine": machine()}
    scenes = {name: make_back(preset(name)) for name in ("normal", "moderate", "severe")}
    report["accuracy_default_noise"] = accuracy(RenderSettings(), scenes)
    report["accuracy_noise_free"] = accuracy(
        RenderSettings(noise=False), {"normal": scenes["normal"]}
    )
    print(json.dumps(report, indent=2), flush=True)

    station = default_station()
    small_r = render(scenes["normal"], station, seed=11)
    small = small_r.image
    report["timing_604x576"] = timings(small, args.repeat, 1.0)
    result = report["timing_604x576"].pop("result")
    report["numbering_604x576"] = numbering_check(result, small_r.line_rows, 1.5)
    from rasterserver_plugins import line_search, peak_detection

    peaks = peak_detection.detect_peaks(small)
    report["profile_604x576"] = {
        "detect_peaks": profile(peak_detection.detect_peaks, (small,), {}, args.repeat),
        "search_lines": profile(
            line_search.search_lines, (peaks.col, peaks.row, peaks.area), {}, args.repeat
        ),
    }
    print(
        json.dumps({k: report[k] for k in ("timing_604x576", "profile_604x576")}, indent=2),
        flush=True,
    )
    if not args.no_large:
        big_station = default_station(width=2048, height=2448)
        t = time.perf_counter()
        big = render(
            scenes["normal"], big_station, settings=RenderSettings(supersampling=1), seed=11
        )
        report["render_2448x2048_s"] = round(time.perf_counter() - t, 1)
        scale = 2048 / 576
        report["timing_2448x2048"] = timings(big.image, max(5, args.repeat // 3), scale)
        result = report["timing_2448x2048"].pop("result")
        report["numbering_2448x2048"] = numbering_check(result, big.line_rows, 1.5 * scale)
        peaks = run_stage(FirstMomentPeaks, Image(big.image), scaled_params(scale)["peaks"])
        exact = truth_rows(peaks.col, peaks.row, big.line_rows, tol=1.5 * scale)
        ok = ~np.isnan(exact)
        err = peaks.row[ok] - exact[ok]
        report["accuracy_2448x2048"] = {
            "peaks": int(peaks.n_peaks),
            "true_centres": len(big.line_rows),
            "matched": int(ok.sum()),
            "rms_px": round(float(np.sqrt(np.mean(err**2))), 4),
        }
        print(json.dumps({k: report[k] for k in report if "2448" in k}, indent=2), flush=True)
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
