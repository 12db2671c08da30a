"""The numbering stage's time per frame: the installed version against earlier versions'
parameters, on the same clinic frames, the variants alternating in one process.

Frames are clinic scenes of :mod:`real_bodies` (read from ``--cache`` where rendered before,
rendered and kept there otherwise); stages 1-3 run once per frame, then the numbering runs
``--repeat`` times per variant, the variants interleaved so that a change of the machine's
load falls on all of them alike. Variants: ``installed`` (the defaults), every ``--variant
NAME=JSON`` (the numbering's parameters, e.g. ``v13={"skip_ratio": 0}``) and, with
``--full-passes``, the installed version whose line-end step judges every end in every
pass (as version 13 was committed; the same refusals, checked on every frame).

Usage::

    python benchmarks/numbering_speed.py --first-seed 8201 --frames 60 --cache /tmp/bodies \\
        --code mseq7 --variant 'v13={"skip_ratio": 0}' --full-passes
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _real_bodies() -> Any:
    return importlib.import_module("real_bodies")  # beside this script; once per process


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--first-seed", type=int, default=8201)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--code", default=None, help="only seeds seen through this code (seed %% 4)")
    ap.add_argument("--raster", default=None, help="see every scene through this raster")
    ap.add_argument("--cache", type=Path, default=None, help="folder of rendered frames")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--variant", action="append", default=[], help="NAME=JSON numbering params")
    ap.add_argument("--full-passes", action="store_true", help="add the full-passes variant")
    args = ap.parse_args(argv)
    from rasterserver_plugins import end_surroundings
    from rasterserver_plugins.line_numbering import CodeWindowNumbering

    from rasterserver.stage import run_stage

    bench = _real_bodies()
    codes = bench.CODES
    seeds = [
        s
        for s in range(args.first_seed, args.first_seed + 100 * args.frames)
        if args.code is None or codes[s % len(codes)] == args.code
    ][: args.frames]
    if args.cache is not None:
        args.cache.mkdir(parents=True, exist_ok=True)
    inputs = []
    for seed in seeds:
        ordered, ctx, _ = bench.ordered_lines(bench.cached_frame(seed, args.raster, args.cache))
        inputs.append((ordered, ctx))
    fast = end_surroundings._one_pass

    def full(*a: Any, changed: Any = None, **k: Any) -> Any:
        return fast(*a, **k)

    variants: dict[str, tuple[dict[str, Any], Any]] = {"installed": ({}, fast)}
    for text in args.variant:
        name, _, params = text.partition("=")
        variants[name] = (json.loads(params), fast)
    if args.full_passes:
        variants["installed, full passes"] = ({}, full)
    times: dict[str, list[float]] = {k: [] for k in variants}
    same = True
    for ordered, ctx in inputs:  # warm: compiled kernels loaded
        run_stage(CodeWindowNumbering, ordered, context=ctx)
    for _ in range(args.repeat):
        for ordered, ctx in inputs:
            numbers = {}
            for name, (params, one_pass) in variants.items():
                end_surroundings._one_pass = one_pass
                t = time.perf_counter()
                out = run_stage(CodeWindowNumbering, ordered, params=params, context=ctx)
                times[name].append(time.perf_counter() - t)
                numbers[name] = out.number
            end_surroundings._one_pass = fast
            if args.full_passes:
                full_numbers = numbers["installed, full passes"]
                same &= bool(np.array_equal(numbers["installed"], full_numbers))
    report = {
        "frames": len(inputs),
        "repeat": args.repeat,
        "version": CodeWindowNumbering.version,
        "ms_median": {k: round(1e3 * float(np.median(v)), 2) for k, v in times.items()},
        "ms_mean": {k: round(1e3 * float(np.mean(v)), 2) for k, v in times.items()},
    }
    if args.full_passes:
        report["full_passes_same_numbers"] = same
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
