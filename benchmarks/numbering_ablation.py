"""What each safeguard of the numbering catches and costs: every step switched off in turn.

On the clinic scenes of :mod:`real_bodies` (read from ``--cache`` where rendered before,
rendered and kept there otherwise), stages 1-3 run once per frame and the numbering runs
with its defaults (``installed``) and once per step with that step switched off by its
parameters (the table of ``docs/numbering-versions.md``). Per variant: the wrongly
numbered peaks (counted against the simulator's truth, as ``real_bodies.py`` counts them),
the scenes with any, and the coverage of the back (the trunk's exact line crossings at or
below the vertebra prominens carrying a peak with its correct number). A step *catches*
the wrong peaks that appear when it is off, and *costs* the back coverage it takes.

The steps were added one at a time, each measured against the version before; their
order matters (a later step judges what the earlier ones left), so a step switched off
alone is measured among all the others, not as it was added. Scenes whose errors move
with the processor (``docs/simulator-scenes.md``) make the figures of one range
comparable on one machine only.

Usage::

    python benchmarks/numbering_ablation.py --first-seed 7600 --scenes 600 \\
        --cache /tmp/bodies --out benchmarks/out/ablation-7600.json
    python benchmarks/numbering_ablation.py --first-seed 7000 --scenes 800 \\
        --raster mseq8b-35to65 --cache /tmp/bodies --only column-islands,line-ends
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

# Each step of the numbering (version that added it) and the parameters that switch it off;
# docs/numbering-versions.md has the same table. Two steps number more rather than refuse
# (bracketed peaks, groups), one spares pairs (pairs confirmed): switched off, they cost
# coverage and may catch nothing. "poor-runs" restores a test version 18 removed.
STEPS: dict[str, tuple[str, dict[str, Any]]] = {
    "code-bands": ("5", {"tile_check": False}),
    "column-neighbours": ("5, 18", {"column_check": False}),
    "beside-doubtful": ("6, 7", {"block_edge_check": False}),
    "stranded-runs": ("6", {"min_run": 0}),
    "column-islands": ("7", {"island_peaks": 0}),
    "bracketed-peaks": ("8", {"bracket_run": 0}),
    "pairs-confirmed": ("9", {"pair_agreement": 0}),
    "line-ends": ("10", {"end_margin": 0, "end_dim": 0}),
    "groups": ("11", {"group_ties": 0}),
    "frame-edges": ("12", {"edge_run": 0}),
    "ends-among-unnumbered": ("13", {"surround_share": 0}),
    "skipped-lines": ("14", {"skip_ratio": 0}),
    "detached-pieces": ("15", {"detached_peaks": 0}),
    "faint-code": ("16, 17", {"faint_ratio": 1}),
    "poor-runs": ("-18", {"poor_run_factor": 2}),
    "final-isolated": ("18", {"final_isolated": False}),
    "column-reading": ("19", {"reading_run": 0}),
    "column-blocks": ("20", {"block_least": 0}),
    "one-sided-lines": ("21", {"one_sided_peaks": 0}),
    "shifted-blocks": ("22", {"pair_shift": False, "shift_block": 0}),
    "one-sided-components": ("23", {"linked_one_sided": 0}),
}


def _real_bodies() -> Any:
    return importlib.import_module("real_bodies")  # beside this script; once per process


_CACHE: Path | None = None
_RASTER: str | None = None
_STEPS: list[str] = []


def _init(cache: Path | None, raster: str | None, steps: list[str]) -> None:
    global _CACHE, _RASTER, _STEPS
    _CACHE, _RASTER, _STEPS = cache, raster, steps


def ablate_scene(seed: int) -> dict[str, Any]:
    """Number scene ``seed`` with the defaults and with each step of ``_STEPS`` off.

    Returns
    -------
    dict
        ``seed``, ``back_crossings`` and per variant ``[wrong peaks, back covered]``.
    """
    from rasterserver_plugins.line_numbering import CodeWindowNumbering

    from rasterserver.stage import run_stage

    bench = _real_bodies()
    frame = bench.cached_frame(seed, _RASTER, _CACHE)
    ordered, ctx, _ = bench.ordered_lines(frame)
    row: dict[str, Any] = {"seed": seed, "back_crossings": int(frame.lr_on_back.sum())}
    for name in ["installed", *_STEPS]:
        params = STEPS[name][1] if name in STEPS else None
        result = run_stage(CodeWindowNumbering, ordered, params=params, context=ctx)
        truth, _ = bench.peak_truth(frame, result)
        wrong = bench.wrong_peaks(result.number, truth)
        covered = bench.covered_crossings(frame, result, truth)
        row[name] = [int(wrong.sum()), int((covered & frame.lr_on_back).sum())]
    return row


def _safe(seed: int) -> dict[str, Any]:
    try:
        return ablate_scene(seed)
    except Exception as exc:  # one bad scene must not end a run of hundreds
        return {"seed": seed, "error": f"{type(exc).__name__}: {exc}"}


def summarise(rows: list[dict[str, Any]], steps: list[str]) -> dict[str, Any]:
    """Totals per variant and each step's catch and cost against the installed numbering.

    Parameters
    ----------
    rows : list of dict
        :func:`ablate_scene`'s rows (rows with an ``error`` are counted apart).
    steps : list of str
        The steps switched off.

    Returns
    -------
    dict
        ``scenes``, ``error_seeds``, ``installed`` and per step: ``wrong_peaks``,
        ``scenes_with_wrong``, ``back_coverage`` (%), and for the steps ``catches`` (wrong
        peaks more with it off) and ``costs_back_points`` (coverage more with it off).
    """
    ok = [r for r in rows if "error" not in r]
    crossings = sum(r["back_crossings"] for r in ok)

    def totals(name: str) -> dict[str, Any]:
        return {
            "wrong_peaks": sum(r[name][0] for r in ok),
            "scenes_with_wrong": sum(1 for r in ok if r[name][0]),
            "back_coverage": round(100.0 * sum(r[name][1] for r in ok) / max(crossings, 1), 4),
        }

    out: dict[str, Any] = {
        "scenes": len(ok),
        "error_seeds": sorted(r["seed"] for r in rows if "error" in r),
        "installed": totals("installed"),
        "steps": {},
    }
    base = out["installed"]
    for name in steps:
        t = totals(name)
        t["version"] = STEPS[name][0]
        t["catches"] = t["wrong_peaks"] - base["wrong_peaks"]
        t["costs_back_points"] = round(t["back_coverage"] - base["back_coverage"], 4)
        out["steps"][name] = t
    return out


def _table(summary: dict[str, Any]) -> str:
    base = summary["installed"]
    lines = [
        f"{summary['scenes']} scenes; installed: {base['wrong_peaks']} wrong peaks in "
        f"{base['scenes_with_wrong']} scenes, back {base['back_coverage']:.4f} %",
        f"{'step switched off':24s} {'version':>8s} {'wrong':>7s} {'scenes':>7s} "
        f"{'back %':>9s} {'catches':>8s} {'costs':>8s}",
    ]
    for name, t in summary["steps"].items():
        lines.append(
            f"{name:24s} {t['version']:>8s} {t['wrong_peaks']:7d} {t['scenes_with_wrong']:7d} "
            f"{t['back_coverage']:9.4f} {t['catches']:8d} {t['costs_back_points']:8.4f}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    from _scene_pool import add_scene_arguments, report, scene_rows, scene_seeds  # beside

    ap = argparse.ArgumentParser(
        description=(__doc__ or "").splitlines()[0],
        epilog="steps: " + ", ".join(STEPS),
    )
    add_scene_arguments(ap)
    ap.add_argument("--only", default=None, help="comma-separated steps (default: all)")
    args = ap.parse_args(argv)
    steps = list(STEPS) if args.only is None else [s.strip() for s in args.only.split(",")]
    unknown = [s for s in steps if s not in STEPS]
    if unknown:
        ap.error(f"unknown step(s) {', '.join(unknown)}; the steps: {', '.join(STEPS)}")
    seeds = scene_seeds(ap, args, _real_bodies()._raster_names())
    rows = scene_rows(
        _safe, seeds, workers=args.workers, initializer=_init,
        initargs=(args.cache, args.raster, steps),
    )  # fmt: skip
    summary = summarise(rows, steps)
    return report(summary, args, _table(summary))


if __name__ == "__main__":
    sys.exit(main())
