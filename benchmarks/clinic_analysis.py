"""The clinical answer on what a clinic's camera sees: the back-shape analysis of clinic
scenes (head, hair, posed arms, clothing) against the same back alone, in one run.

Per seed, :func:`rasterserver.simulator.body.random_body` is seen through
:func:`rasterserver.simulator.body.clinic_station` with the seed's diapositive code (as in
``real_bodies.py``) and rendered twice with the same station, light and sensor noise:

* ``body``: the whole clinic scene (:func:`~rasterserver.simulator.body.make_body`);
* ``back``: its back alone (:func:`~rasterserver.simulator.back.make_back`: trunk and
  hanging arms, no head, hair, posed arms or clothing), what the analysis was tuned on.

Both go through the installed chain to the analysis (``run_chain(..., until="analysis")``)
and are scored against the same truth by ``analysis.py``'s :func:`score` (landmarks VP,
DL, DR, DM, SP; the spinal midline; the surface rotation; the parameters). The summary
counts, per landmark, how often each kind finds it (in view, 30 px or more inside the
frame), its error, and the scenes where the back alone finds it and the body does not:
what head, hair, arms and clothing cost the clinical answer. The refusals' reasons are
tallied (a refusal is the safe answer; a wrong landmark would not be).

One JSON line per (seed, kind) is appended to ``--out`` as soon as it is done; a rerun
resumes, and rows of other analysis code (``analysis.analysis_code``) or other ``--params``
are refused.

Usage::

    python benchmarks/clinic_analysis.py --first-seed 0 --scenes 100 --out /tmp/ca.jsonl
    python benchmarks/clinic_analysis.py --first-seed 0 --scenes 100 --out /tmp/ca3.jsonl \\
        --params '{"analysis": {"vp_axis_offset": 0}}'      # analysis version 3
    python benchmarks/clinic_analysis.py --summary /tmp/ca.jsonl
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import multiprocessing as mp  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _resume import read_rows  # noqa: E402

KINDS = ("body", "back")
_PARAMS: dict[str, dict[str, Any]] = {}


def _init(params: dict[str, dict[str, Any]] | None) -> None:
    """Worker start: the chain's stage parameters (``--params``)."""
    _PARAMS.clear()
    _PARAMS.update(params or {})


def _bench(name: str) -> Any:
    return importlib.import_module(name)  # a script beside this one; once per process


def run_scene(task: tuple[int, str]) -> dict[str, Any]:
    """Render, reconstruct, analyse and score one scene of one kind."""
    from rasterserver.pipeline import run_chain
    from rasterserver.simulator.back import make_back
    from rasterserver.simulator.back_truth import truth
    from rasterserver.simulator.body import clinic_station, make_body, random_body
    from rasterserver.simulator.render import render
    from rasterserver.stage import StageContext

    seed, kind = task
    analysis = _bench("analysis")
    code = _bench("real_bodies").CODES[seed % 4]
    params = random_body(seed)
    station = clinic_station(seed, code)
    context = StageContext(calibration=station, raster=station.raster_definition)
    t0 = time.perf_counter()
    scene = make_body(params) if kind == "body" else make_back(params.back)
    settings = _bench("numbering_backs")._settings(seed).replace(threads=1)
    image = render(scene, station, settings=settings, seed=seed).image
    t1 = time.perf_counter()
    shape = run_chain(image, context=context, until="analysis", params=_PARAMS or None)[
        "analysis"
    ]
    return {
        "seed": seed,
        "kind": kind,
        "code_raster": code,
        "posture": str(params.arm_posture),
        "waistband": params.waistband is not None,
        "head": bool(params.head),
        "straight": not params.back.curves,
        "render_s": round(t1 - t0, 3),
        "chain_s": round(time.perf_counter() - t1, 3),
        **analysis.score(shape, truth(scene), station.camera),
    }


def _safe(task: tuple[int, str]) -> dict[str, Any]:
    try:
        return run_scene(task)
    except Exception as exc:  # a crash is a result too: count it, keep going
        return {"seed": task[0], "kind": task[1], "error": f"{type(exc).__name__}: {exc}"}


def _rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if values else math.nan


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per kind: landmarks found and their errors, midline, refusals; and the pairs' losses."""
    analysis = _bench("analysis")
    edge = analysis.EDGE_PX
    by = {(r["seed"], r["kind"]): r for r in rows}
    seeds = sorted({s for s, k in by if all((s, kk) in by for kk in KINDS)})
    out: dict[str, Any] = {"scenes": len(seeds)}
    for kind in KINDS:
        sel = [by[(s, kind)] for s in seeds]
        ok = [r for r in sel if "error" not in r]
        entry: dict[str, Any] = {
            "crashed": [f"{r['seed']}: {r['error']}" for r in sel if "error" in r],
            "no_answer": sum(1 for r in ok if r["reason"]),
        }
        for name in analysis.LANDMARK_NAMES:
            inner = [r["landmarks"][name] for r in ok if r["landmarks"][name]["edge_px"] >= edge]
            errors = [float(np.linalg.norm(e["error"])) for e in inner if e["found"]]
            entry[name] = {
                "in_view": len(inner),
                "found": len(errors),
                "rms_mm": _rms(errors),
                "p95_mm": float(np.percentile(errors, 95)) if errors else math.nan,
                "max_mm": max(errors, default=math.nan),
            }
        mids = [r["midline"] for r in ok if r.get("midline")]
        entry["midline"] = {"found": len(mids), "rms_mm": _rms([m["rms_mm"] for m in mids])}
        reasons = Counter()
        for r in ok:
            for name in analysis.LANDMARK_NAMES:
                e = r["landmarks"][name]
                if e["edge_px"] >= edge and not e["found"]:
                    why = str(e.get("reason") or "refused")
                    reasons[f"{name}: {why.split('(')[0].strip()[:90]}"] += 1
        entry["refusals"] = dict(reasons.most_common(12))
        out[kind] = entry
    lost: dict[str, list[int]] = {}
    worse: dict[str, list[int]] = {}
    for name in analysis.LANDMARK_NAMES:
        lost[name], worse[name] = [], []
        for s in seeds:
            a, b = by[(s, "body")], by[(s, "back")]
            if "error" in a or "error" in b:
                continue
            ea, eb = a["landmarks"][name], b["landmarks"][name]
            if eb["edge_px"] < edge or not eb["found"]:
                continue
            if not ea["found"]:
                lost[name].append(s)
            elif np.linalg.norm(ea["error"]) > np.linalg.norm(eb["error"]) + 5.0:
                worse[name].append(s)
    out["lost_by_body"] = lost
    out["worse_by_body_over_5mm"] = worse
    return out


def markdown(s: dict[str, Any]) -> str:
    """The summary as a markdown table (landmarks found in view and their rms error)."""
    names = _bench("analysis").LANDMARK_NAMES
    head = "| | " + " | ".join(names) + " | midline |"
    lines = [head, "|---" * (len(names) + 2) + "|"]
    for kind in KINDS:
        e = s[kind]
        cells = [
            f"{e[n]['found']}/{e[n]['in_view']}, {e[n]['rms_mm']:.1f} mm"
            for n in names
        ]
        mid = f"{e['midline']['found']}, {e['midline']['rms_mm']:.2f} mm"
        lines.append(f"| {kind} | " + " | ".join(cells) + f" | {mid} |")
    lost = s["lost_by_body"]
    lines.append(
        "| lost by the body (back alone finds it) | "
        + " | ".join(str(len(lost[n])) for n in names)
        + " | |"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--scenes", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/clinic-analysis.jsonl"))
    ap.add_argument("--summary", type=Path, default=None, help="only summarise this file")
    ap.add_argument(
        "--params",
        default=None,
        help='stage parameters, JSON: {"analysis": {"vp_axis_offset": 0}} (version 3)',
    )
    args = ap.parse_args(argv)
    if args.summary is not None:
        s = summary(read_rows(args.summary))
        print(json.dumps(s, indent=2))
        print(markdown(s))
        return 0
    if args.scenes < 1:
        ap.error("--scenes must be at least 1")
    try:
        params = json.loads(args.params) if args.params else None
    except json.JSONDecodeError as exc:
        ap.error(f"--params is not JSON: {exc}")
    stamp = _bench("analysis").analysis_code() + (f" {json.dumps(params)}" if params else "")
    rows = read_rows(args.out)
    if any(r.get("stamp") != stamp for r in rows):
        ap.error(f"{args.out} holds rows of other analysis code or --params; give another --out")
    done = {(r["seed"], r["kind"]) for r in rows}
    seeds = range(args.first_seed, args.first_seed + args.scenes)
    todo = [(s, k) for s in seeds for k in KINDS if (s, k) not in done]
    print(f"{len(done)} done, {len(todo)} to go", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    start = time.time()
    with (
        mp.get_context("spawn").Pool(
            args.workers, initializer=_init, initargs=(params,), maxtasksperchild=40
        ) as pool,
        args.out.open("a") as fh,
    ):
        for i, res in enumerate(pool.imap_unordered(_safe, todo, chunksize=1), 1):
            fh.write(json.dumps({**res, "stamp": stamp}) + "\n")
            fh.flush()
            if i % 20 == 0 or res.get("error"):
                rate = (time.time() - start) / i
                print(f"{i}/{len(todo)} {res.get('error') or ''} {rate:.2f} s each", flush=True)
    s = summary(read_rows(args.out))
    print(json.dumps(s, indent=2))
    print(markdown(s))
    return 0


if __name__ == "__main__":
    sys.exit(main())
