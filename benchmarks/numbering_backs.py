"""Wrongly numbered lines over many varied simulated backs (stages 1-4 against the truth).

Every back is drawn by :func:`rasterserver.simulator.back.random_back` (normal to severe
scoliosis, varied size, posture, position, skin albedo) and rendered with a randomly varied
light level and sensor noise; the image goes through peak detection, line search, line
sequence analysis and line numbering, and every numbered line is checked against the
simulator's exact line numbers.

Per back (one JSON line each, appended as soon as the back is done, so a run can be
interrupted and resumed):

* ``lines``: lines found; ``true_lines``: lines with a ground-truth number (their peaks
  lie on exact line centres);
* ``numbered``, ``wrong`` (a numbered line whose majority ground-truth number differs),
  ``unnumbered`` (a line with a true number but no number);
* ``coverage``: share of the visible line-centre samples (every column crossing of a
  visible raster line, from the simulator) that carry a detected peak with its correct
  number; ``peak_coverage``: share of true peaks numbered; ``wrong_peaks``.

Usage::

    python benchmarks/numbering_backs.py --backs 1200 --workers 2 \
        --out benchmarks/out/numbering.jsonl
    python benchmarks/numbering_backs.py --summary benchmarks/out/numbering.jsonl
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import multiprocessing as mp  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402


def _settings(seed: int) -> Any:
    from rasterserver.simulator.render import RenderSettings

    rng = np.random.default_rng([seed, 0xBEEF])
    return RenderSettings(
        supersampling=1,
        projector_electrons=float(rng.uniform(15000.0, 45000.0)),
        ambient_electrons=float(rng.uniform(300.0, 1500.0)),
        read_noise=float(rng.uniform(8.0, 25.0)),
        projector_defocus=float(rng.uniform(0.4, 0.9)),
        camera_blur=float(rng.uniform(0.35, 0.7)),
    )


def _truth_numbers(
    col: np.ndarray, row: np.ndarray, lr: Any, tol: float = 1.5, resolve: float = 3.0
) -> np.ndarray:
    """True line number of each peak; -1 when no line centre is within ``tol`` px, or when
    two line centres lie closer than ``resolve`` px (a line emerging from behind a fold:
    one peak, and no telling which line it is)."""
    gc, gr, gn = lr.column, lr.row, lr.number
    order = np.lexsort((gr, gc))
    kg = gc[order].astype(np.int64) * 1e5 + gr[order]
    gn = gn[order]
    kp = col.astype(np.int64) * 1e5 + row
    if kg.size == 0 or kp.size == 0:
        return np.full(kp.size, -1, np.int64)
    last = kg.size - 1
    j = np.clip(np.searchsorted(kg, kp), 1, max(last, 1))
    j0, j1 = np.clip(j - 1, 0, last), np.clip(j, 0, last)
    e0, e1 = np.abs(kg[j0] - kp), np.abs(kg[j1] - kp)
    jj = np.where(e0 < e1, j0, j1)
    near = np.minimum(e0, e1) < tol
    for side in (np.clip(jj - 1, 0, last), np.clip(jj + 1, 0, last)):
        near &= ~((side != jj) & (np.abs(kg[side] - kg[jj]) < resolve))
    return np.where(near, gn[jj], -1)


def run_back(seed: int) -> dict[str, Any]:
    """Render back ``seed``, run stages 1-4, score against the truth."""
    from rasterserver_plugins.line_numbering import CodeWindowNumbering
    from rasterserver_plugins.line_search import HierarchicalLineSearch
    from rasterserver_plugins.line_sequence import HierarchicalLineOrder
    from rasterserver_plugins.peak_detection import FirstMomentPeaks

    from rasterserver.optics import default_station
    from rasterserver.records import Image
    from rasterserver.simulator.back import make_back, random_back
    from rasterserver.simulator.render import render
    from rasterserver.stage import StageContext, run_stage

    station = default_station()
    params = random_back(seed)
    t0 = time.perf_counter()
    rendering = render(make_back(params), station, settings=_settings(seed), seed=seed)
    t1 = time.perf_counter()
    ctx = StageContext(raster=station.raster_definition)
    times = []
    t = time.perf_counter()
    peaks = run_stage(FirstMomentPeaks, Image(rendering.image), params=_PARAMS.get("peaks"))
    times.append(time.perf_counter() - t)
    t = time.perf_counter()
    lines = run_stage(HierarchicalLineSearch, peaks, params=_PARAMS.get("lines"))
    times.append(time.perf_counter() - t)
    t = time.perf_counter()
    ordered = run_stage(HierarchicalLineOrder, lines, params=_PARAMS.get("order"))
    times.append(time.perf_counter() - t)
    t = time.perf_counter()
    result = run_stage(CodeWindowNumbering, ordered, params=_PARAMS.get("numbers"), context=ctx)
    times.append(time.perf_counter() - t)

    lr = rendering.line_rows
    number = _truth_numbers(result.col, result.row, lr)
    n_lines = int(result.line_order.size)
    wrong = numbered = unnumbered = true_lines = 0
    wrong_list = []
    for line in range(n_lines):
        truth = number[(result.line_id == line) & (number >= 0)]
        if truth.size == 0:
            continue
        true_lines += 1
        majority = int(np.bincount(truth).argmax())
        if result.line_number[line] >= 0:
            numbered += 1
            if majority != int(result.line_number[line]):
                wrong += 1
                wrong_list.append([line, majority, int(result.line_number[line]), int(truth.size)])
        else:
            unnumbered += 1
    on_line = number >= 0
    correct = on_line & (result.number == number)
    wrong_peaks = int(np.count_nonzero((result.number >= 0) & on_line & (result.number != number)))
    curves = params.curves
    return {
        "seed": seed,
        "max_deviation_mm": float(max((abs(c.lateral_deviation) for c in curves), default=0.0)),
        "max_rotation_deg": float(max((abs(c.rotation) for c in curves), default=0.0)),
        "peaks": int(result.n_peaks),
        "lines": n_lines,
        "true_lines": true_lines,
        "numbered": numbered,
        "wrong": wrong,
        "wrong_lines": wrong_list,
        "unnumbered": unnumbered,
        "wrong_peaks": wrong_peaks,
        "coverage": float(np.count_nonzero(correct) / max(len(lr), 1)),
        "peak_coverage": float(np.count_nonzero(correct) / max(np.count_nonzero(on_line), 1)),
        "confidence": float(result.confidence),
        "reason": result.reason,
        "stage_ms": [round(1e3 * x, 3) for x in times],
        "render_s": round(t1 - t0, 3),
    }


# per-stage parameters (``--params``), to compare a plugin's settings on the same backs
_PARAMS: dict[str, dict[str, Any]] = {}


def _init(params: dict[str, dict[str, Any]] | None) -> None:
    global _PARAMS
    _PARAMS = params or {}


def _safe(seed: int) -> dict[str, Any]:
    try:
        return run_back(seed)
    except Exception as exc:  # a crash is a result too: count it, keep going
        return {"seed": seed, "error": f"{type(exc).__name__}: {exc}"}


def summary(path: Path) -> dict[str, Any]:
    """Totals over the JSON lines in ``path``."""
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    ok = [r for r in rows if "error" not in r]
    tot = {
        k: int(sum(r[k] for r in ok))
        for k in ("lines", "true_lines", "numbered", "wrong", "unnumbered", "wrong_peaks", "peaks")
    }
    stage_ms = np.array([r["stage_ms"] for r in ok]) if ok else np.zeros((0, 4))
    return {
        "backs": len(rows),
        "errors": len(rows) - len(ok),
        **tot,
        "backs_with_wrong_lines": sum(1 for r in ok if r["wrong"] > 0),
        "backs_fully_numbered": sum(1 for r in ok if r["unnumbered"] == 0),
        "coverage_mean": float(np.mean([r["coverage"] for r in ok])) if ok else 0.0,
        "coverage_p5": float(np.percentile([r["coverage"] for r in ok], 5)) if ok else 0.0,
        "coverage_min": float(np.min([r["coverage"] for r in ok])) if ok else 0.0,
        "peak_coverage_mean": float(np.mean([r["peak_coverage"] for r in ok])) if ok else 0.0,
        "peaks_median": float(np.median([r["peaks"] for r in ok])) if ok else 0.0,
        "stage_ms_median": np.median(stage_ms, axis=0).round(2).tolist() if ok else [],
        "wrong_seeds": [r["seed"] for r in ok if r["wrong"] > 0][:50],
    }


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backs", type=int, default=1200)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/numbering.jsonl"))
    ap.add_argument("--summary", type=Path, default=None, help="only summarise this file")
    ap.add_argument(
        "--params",
        default=None,
        help='stage parameters, JSON: {"peaks": {...}, "numbers": {...}} (default: installed)',
    )
    args = ap.parse_args(argv)
    if args.summary is not None:
        print(json.dumps(summary(args.summary), indent=2))
        return 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    from _resume import chain_stamp, done_seeds  # beside this script

    stamp = chain_stamp(json.loads(args.params) if args.params else None)
    done = done_seeds(args.out, stamp)
    todo = [s for s in range(args.first_seed, args.first_seed + args.backs) if s not in done]
    print(f"{len(done)} backs done, {len(todo)} to go", flush=True)
    start = time.time()
    with (
        mp.get_context("spawn").Pool(
            args.workers,
            initializer=_init,
            initargs=(json.loads(args.params) if args.params else None,),
            maxtasksperchild=50,
        ) as pool,
        args.out.open("a") as fh,
    ):
        for i, res in enumerate(pool.imap_unordered(_safe, todo, chunksize=1), 1):
            fh.write(json.dumps({**res, "stamp": stamp}) + "\n")
            fh.flush()
            if i % 20 == 0 or res.get("wrong") or res.get("error"):
                rate = (time.time() - start) / i
                print(
                    f"{i}/{len(todo)} seed {res['seed']} wrong {res.get('wrong')} "
                    f"err {res.get('error')} {rate:.2f} s/back",
                    flush=True,
                )
    print(json.dumps(summary(args.out), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
