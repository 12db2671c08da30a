"""Back-shape analysis against the simulator's truth: landmarks, midline, rotation, parameters.

Every back is rendered with the default station (604 x 576) under varied light and sensor
noise, reconstructed to the smoothed surface (``run_chain(..., until="surface")``) and
analysed by the installed ``analysis`` stage; the result is scored against
:func:`rasterserver.simulator.back_truth.truth` (definitions in ``docs/simulator_truth.md``):

* landmarks VP, DL, DR, DM, SP: 3-D error (mm) when found; found / refused and why, split by
  where the true landmark lies in the image (well inside, within 30 px of the border, outside);
* the spinal midline in the frontal plane against the true vertebral-body centres at the same
  height (the lateral-deviation error, mm), the largest lateral deviation against the true
  one, the surface rotation along the symmetry line against the true one (degrees); for the
  straight backs the largest error of both (the truth is zero there, apart from the posture's
  turn);
* every parameter the analysis reports under a name of the truth (``kyphotic_angle_deg`` or
  ``kyphotic_angle``): bias, rms, 95th percentile of the error;
* repeatability: each of ``--repeat-backs`` backs re-rendered ``--repeats`` times with
  independent noise and a posture sway of up to ±5 mm / ±1° (:func:`posture_sway`): the
  standard deviation of every parameter over the repeats (the smallest detectable change),
  beside the standard deviation of its truth (what the sway itself changes);
* time of the analysis stage alone, on one thread (BLAS/OpenMP set to one thread before
  numpy is imported), in the workers and, undisturbed, in a final sequential pass.

Sets: **tuning** (the presets normal, moderate, severe and ``random_back`` seeds 0 to
``count - 1``) and **held-out** (seeds 1000 to ``1000 + count - 1``), reported separately.
Random backs also lean sideways and turn a little (drawn from the seed). The analysis is tuned
on the tuning set only; nobody tuning it looks at the held-out figures.

Per acquisition one JSON line is appended to ``<out>.jsonl`` as soon as it is done (an
interrupted run resumes); the summary goes to ``<out>`` (JSON) and a markdown report to
``<out>.md`` (``--write`` adds it as the newest subsection of "Back-shape analysis" in
BENCHMARKS.md, keeping the older ones).

Usage::

    python benchmarks/analysis.py --out benchmarks/out/analysis.json            # 203 + 100 backs
    python benchmarks/analysis.py --quick --out /tmp/analysis-quick.json        # a few minutes
    python benchmarks/analysis.py --seeds 0-9 --repeat-backs 0 --out /tmp/a.json  # tuning only
    python benchmarks/analysis.py --summary benchmarks/out/analysis.json --write
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import multiprocessing as mp  # noqa: E402
import re  # noqa: E402
import sys  # noqa: E402
import textwrap  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import add_write_options, machine, subsection_heading, write_subsection  # noqa: E402

TITLE = "Back-shape analysis"
LANDMARK_NAMES = ("VP", "DL", "DR", "DM", "SP")
PRESET_NAMES = ("normal", "moderate", "severe")
HELD_OUT_FIRST_SEED = 1000
#: A true landmark closer than this to the image border (px) counts as "at the edge".
EDGE_PX = 30.0
TARGETS = {
    "landmark_rms_mm": 2.0,
    "midline_rms_mm": 2.0,
    "deviation_max_error_mm": 2.0,
    "rotation_rms_deg": 1.5,
    "straight_deviation_max_mm": 1.0,
    "straight_rotation_max_deg": 1.0,
    "analysis_ms": 100.0,
}


# ------------------------------------------------------------------------------ the backs


def back_params(back: str) -> Any:
    """The parameters of back ``back``: a preset name or ``random-<seed>``.

    Random backs get a lateral lean (σ 1.5°) and a turn (σ 2°) on top of
    :func:`random_back`'s posture, drawn from the seed.
    """
    from rasterserver.simulator.back import preset, random_back

    if back in PRESET_NAMES:
        return preset(back)
    seed = int(back.removeprefix("random-"))
    rng = np.random.default_rng([seed, 0xB0D7])
    return dataclasses.replace(
        random_back(seed),
        lateral_lean=float(np.clip(rng.normal(0.0, 1.5), -5.0, 5.0)),
        turn=float(np.clip(rng.normal(0.0, 2.0), -6.0, 6.0)),
    )


def _back_seed(back: str) -> int:
    return PRESET_NAMES.index(back) + 1 if back in PRESET_NAMES else int(back.split("-")[1])


def render_settings(back: str) -> Any:
    """Light, blur and sensor noise of back ``back`` (the same for all its repeats)."""
    from rasterserver.simulator.render import RenderSettings

    if back in PRESET_NAMES:
        return RenderSettings(threads=1)
    rng = np.random.default_rng([_back_seed(back), 0xBEEF])
    return RenderSettings(
        projector_electrons=float(rng.uniform(15000.0, 45000.0)),
        ambient_electrons=float(rng.uniform(300.0, 1500.0)),
        read_noise=float(rng.uniform(8.0, 25.0)),
        projector_defocus=float(rng.uniform(0.4, 0.9)),
        camera_blur=float(rng.uniform(0.35, 0.7)),
        threads=1,
    )


def tasks(
    count: int, seeds: list[int] | None, repeat_backs: int, repeats: int
) -> list[tuple[str, str, int]]:
    """The acquisitions to make: ``(set, back, repeat)``; repeat -1 for the accuracy run."""
    out: list[tuple[str, str, int]] = []
    if seeds is None:
        out += [("tuning", name, -1) for name in PRESET_NAMES]
        seeds = list(range(count)) + list(range(HELD_OUT_FIRST_SEED, HELD_OUT_FIRST_SEED + count))
    for seed in seeds:
        kind = "held-out" if seed >= HELD_OUT_FIRST_SEED else "tuning"
        out.append((kind, f"random-{seed}", -1))
    # Repeatability on tuning backs: the presets first, then random seeds from 0.
    backs = [*PRESET_NAMES, *(f"random-{s}" for s in range(max(repeat_backs - 3, 0)))]
    for back in backs[:repeat_backs]:
        out += [("repeat", back, k) for k in range(repeats)]
    return out


def _key(task: tuple[str, str, int] | dict[str, Any]) -> str:
    if isinstance(task, dict):
        return f"{task['set']}:{task['back']}:{task['repeat']}"
    return f"{task[0]}:{task[1]}:{task[2]}"


# ------------------------------------------------------------------------------ scoring


def _edge_px(camera: Any, point: np.ndarray) -> float:
    """Distance (px) of a world point's image inside the border; negative outside."""
    u, v = camera.project(np.asarray(point, dtype=float)[None])[0]
    h, w = camera.shape
    if not (math.isfinite(u) and math.isfinite(v)):
        return -math.inf
    return float(min(u + 0.5, v + 0.5, w - 0.5 - u, h - 0.5 - v))


def _reason(reasons: dict[str, str], name: str) -> str | None:
    if name in reasons:
        return reasons[name]
    for key, why in reasons.items():
        if key.split(".")[0].split(":")[0].strip() == name:
            return why
    return None


def _lookup(table: dict[str, Any], name: str) -> tuple[str, dict[str, Any]] | None:
    """The analysis's entry for truth parameter ``name`` (same name, or without unit suffix)."""
    candidates = [name]
    for suffix in ("_deg", "_mm"):
        if name.endswith(suffix):
            candidates.append(name.removesuffix(suffix))
    for c in candidates:
        if c in table and isinstance(table[c], dict):
            return c, table[c]
    return None


def _finite_rows(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    return np.isfinite(a).all(axis=1) if a.ndim == 2 else np.isfinite(a)


def score(shape: Any, tr: dict[str, Any], camera: Any) -> dict[str, Any]:
    """Compare one BackShape with the truth of its scene."""
    from rasterserver.simulator.back_truth import signed_extremes

    reasons = shape.reason_table()
    out: dict[str, Any] = {"reason": shape.reason, "reasons": reasons, "landmarks": {}}
    for i, name in enumerate(LANDMARK_NAMES):
        true = tr["landmarks"][name]
        found = shape.landmark(name)
        out["landmarks"][name] = {
            "edge_px": round(_edge_px(camera, true), 1),
            "found": found is not None,
            "error": None if found is None else (found - true).round(3).tolist(),
            "confidence": float(shape.landmark_confidence[i]),
            "reason": None if found is not None else _reason(reasons, name),
        }

    spine = tr["spine"]
    body, skin = spine["body"], spine["skin"]
    vp, dm = tr["landmarks"]["VP"], tr["landmarks"]["DM"]
    truth_dev = signed_extremes(spine["lateral_deviation_mm"])[1]
    truth_rot = signed_extremes(spine["surface_rotation_deg"])[1]
    out["truth_deviation_max_mm"] = truth_dev
    out["truth_rotation_max_deg"] = truth_rot

    mid = np.asarray(shape.midline, dtype=float)
    mid = mid[_finite_rows(mid)] if mid.size else np.zeros((0, 3))
    inside = (mid[:, 1] >= body[0, 1]) & (mid[:, 1] <= body[-1, 1]) if len(mid) else []
    if len(mid) and np.count_nonzero(inside) >= 2:
        m = mid[inside]
        err = m[:, 0] - np.interp(m[:, 1], body[:, 1], body[:, 0])
        line_x = vp[0] + (dm[0] - vp[0]) * (m[:, 1] - vp[1]) / (dm[1] - vp[1])
        dev = m[:, 0] - line_x
        _, _, pos, neg = signed_extremes(dev)
        _, _, true_pos, true_neg = signed_extremes(spine["lateral_deviation_mm"])
        out["midline"] = {
            "rms_mm": float(np.sqrt(np.mean(err**2))),
            "max_abs_mm": float(np.abs(err).max()),
            "coverage": float((m[-1, 1] - m[0, 1]) / (body[-1, 1] - body[0, 1])),
            "deviation_max_mm": signed_extremes(dev)[1],
            # per side: the signed maximum flips where both sides are nearly equal
            "deviation_max_error_mm": max(pos - true_pos, neg - true_neg, key=abs),
        }
    else:
        out["midline"] = None

    sym = np.asarray(shape.symmetry_line, dtype=float)
    rot = np.asarray(shape.surface_rotation, dtype=float)
    ok = _finite_rows(sym) & np.isfinite(rot) if sym.size else np.zeros(0, bool)
    if np.count_nonzero(ok) >= 2:
        y, r = sym[ok, 1], rot[ok]
        keep = (y >= skin[0, 1]) & (y <= skin[-1, 1])
        if np.count_nonzero(keep) >= 2:
            err = r[keep] - np.interp(y[keep], skin[:, 1], spine["surface_rotation_deg"])
            out["rotation"] = {
                "rms_deg": float(np.sqrt(np.mean(err**2))),
                "max_abs_deg": float(np.abs(err).max()),
                "max_deg": signed_extremes(r[keep])[1],
                "max_error_deg": signed_extremes(r[keep])[1] - truth_rot,
            }
        else:
            out["rotation"] = None
    else:
        out["rotation"] = None

    table = shape.parameter_table()
    params: dict[str, Any] = {}
    matched = set()
    for name, entry in tr["parameters"].items():
        hit = _lookup(table, name)
        value = None
        if hit is not None:
            matched.add(hit[0])
            v = hit[1].get("value")
            value = float(v) if isinstance(v, int | float) and math.isfinite(v) else None
        params[name] = {"truth": entry["value"], "value": value}
    out["parameters"] = params
    out["unmatched_parameters"] = sorted(set(table) - matched)
    return out


# ------------------------------------------------------------------------------ one back

_STATE: dict[str, Any] = {}


def analysis_code() -> str:
    """The installed analysis plugin and a hash of its package's sources.

    Rows made by other code are neither reused on resuming nor summarised, so a run never
    mixes versions of an analysis that is being changed.
    """
    import hashlib

    import rasterserver_plugins

    from rasterserver.registry import get_registry

    stage = get_registry().default_for("analysis")
    digest = hashlib.sha256()
    for path in sorted(Path(rasterserver_plugins.__file__).parent.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return f"{stage.name} {stage.version} {digest.hexdigest()[:12]}"


def _station() -> tuple[Any, Any]:
    if "station" not in _STATE:
        from rasterserver.optics import default_station
        from rasterserver.stage import StageContext

        station = default_station()
        _STATE["station"] = station
        _STATE["context"] = StageContext(calibration=station, raster=station.raster_definition)
        _STATE["code"] = analysis_code()
    return _STATE["station"], _STATE["context"]


def _init(params: dict[str, dict[str, Any]] | None) -> None:
    """Worker start: the chain's stage parameters (``--params``), None for the defaults."""
    _STATE["params"] = params


def run_task(task: tuple[str, str, int]) -> dict[str, Any]:
    """Render, reconstruct, analyse and score one acquisition."""
    from rasterserver.pipeline import run_chain
    from rasterserver.simulator.back import make_back, posture_sway
    from rasterserver.simulator.back_truth import truth
    from rasterserver.simulator.render import render

    kind, back, repeat = task
    station, context = _station()
    params = back_params(back)
    noise_seed = _back_seed(back)
    if repeat >= 0:
        params = posture_sway(params, 7919 * _back_seed(back) + repeat)
        noise_seed = 100_000 + 1000 * _back_seed(back) + repeat
    t0 = time.perf_counter()
    scene = make_back(params)
    tr = truth(scene)
    rendering = render(scene, station, settings=render_settings(back), seed=noise_seed)
    t1 = time.perf_counter()
    durations: dict[str, float] = {}
    # each of the two chains takes only its own stages' parameters (run_chain refuses others)
    stage_params = _STATE.get("params") or {}
    surface = run_chain(
        rendering.image,
        context=context,
        until="surface",
        durations=durations,
        params={k: v for k, v in stage_params.items() if k != "analysis"} or None,
    )["surface"]
    t2 = time.perf_counter()
    shape = run_chain(
        surface,
        context=context,
        until="analysis",
        durations=durations,
        params={k: v for k, v in stage_params.items() if k == "analysis"} or None,
    )["analysis"]
    curves = params.curves
    result = {
        "set": kind,
        "back": back,
        "repeat": repeat,
        "straight": not curves,
        "trunk_length": params.trunk_length,
        "max_curve_deviation_mm": max((abs(c.lateral_deviation) for c in curves), default=0.0),
        "max_curve_rotation_deg": max((abs(c.rotation) for c in curves), default=0.0),
        "turn_deg": params.turn,
        "render_s": round(t1 - t0, 3),
        "chain_s": round(t2 - t1, 3),
        "analysis_ms": round(1e3 * durations["analysis"], 3),
        "code": _STATE["code"],
        **score(shape, tr, station.camera),
    }
    return result


def _safe(task: tuple[str, str, int]) -> dict[str, Any]:
    try:
        return run_task(task)
    except Exception as exc:  # a crash is a result too: count it, keep going
        return {
            "set": task[0],
            "back": task[1],
            "repeat": task[2],
            "code": _STATE.get("code") or analysis_code(),
            "error": f"{type(exc).__name__}: {exc}",
        }


# ------------------------------------------------------------------------------ summary


def _rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if values else math.nan


def _p95(values: list[float]) -> float:
    return float(np.percentile(np.abs(values), 95)) if values else math.nan


def _max(values: list[float]) -> float:
    return float(np.max(np.abs(values))) if values else math.nan


def _why(entry: dict[str, Any]) -> str:
    """A refusal's reason with its numbers made N, so that alike reasons count together."""
    return re.sub(r"-?\d+(\.\d+)?", "N", entry["reason"] or "(no reason)")


def _errors(rows: list[dict[str, Any]], name: str) -> list[float]:
    """Analysis − truth of parameter ``name`` over the rows where the analysis gave it."""
    return [
        r["parameters"][name]["value"] - r["parameters"][name]["truth"]
        for r in rows
        if r["parameters"][name]["value"] is not None
    ]


def summarise_set(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Accuracy figures over the accuracy rows of one set."""
    ok = [r for r in rows if "error" not in r]
    out: dict[str, Any] = {
        "backs": len(rows),
        "crashed": len(rows) - len(ok),
        "crashes": [f"{r['back']}: {r['error']}" for r in rows if "error" in r][:10],
        "empty": sum(1 for r in ok if r["reason"]),
        "empty_reasons": dict(Counter(r["reason"] for r in ok if r["reason"]).most_common(10)),
    }
    landmarks: dict[str, Any] = {}
    for name in LANDMARK_NAMES:
        entries = [r["landmarks"][name] for r in ok]
        inner = [e for e in entries if e["edge_px"] >= EDGE_PX]
        edge = [e for e in entries if 0.0 <= e["edge_px"] < EDGE_PX]
        outside = [e for e in entries if e["edge_px"] < 0.0]
        errors = [float(np.linalg.norm(e["error"])) for e in inner if e["found"]]
        axes = np.array([e["error"] for e in inner if e["found"]]).reshape(-1, 3)
        landmarks[name] = {
            "in_view": len(inner),
            "found_in_view": sum(e["found"] for e in inner),
            "at_edge": len(edge),
            "found_at_edge": sum(e["found"] for e in edge),
            "out_of_view": len(outside),
            "found_out_of_view": sum(e["found"] for e in outside),
            "rms_mm": _rms(errors),
            "p95_mm": _p95(errors),
            "max_mm": _max(errors),
            "bias_mm": axes.mean(axis=0).round(2).tolist() if len(axes) else None,
            "refusals_in_view": dict(Counter(_why(e) for e in inner if not e["found"])),
            "refusals_elsewhere": dict(Counter(_why(e) for e in edge + outside if not e["found"])),
        }
    out["landmarks"] = landmarks
    found = [
        float(np.linalg.norm(r["landmarks"][n]["error"]))
        for r in ok
        for n in ("VP", "DL", "DR")
        if r["landmarks"][n]["found"] and r["landmarks"][n]["edge_px"] >= EDGE_PX
    ]
    out["vp_dl_dr_rms_mm"] = _rms(found)

    mids = [r["midline"] for r in ok if r["midline"]]
    # The largest lateral deviation the analysis reports, per side (the signed maximum flips
    # where both sides are nearly equal): the worse of the errors of +max and -max.
    extreme = [
        max(
            (
                r["parameters"][n]["value"] - r["parameters"][n]["truth"]
                for n in ("lateral_deviation_pos_max_mm", "lateral_deviation_neg_max_mm")
                if r["parameters"][n]["value"] is not None
            ),
            key=abs,
            default=math.nan,
        )
        for r in ok
    ]
    extreme = [e for e in extreme if math.isfinite(e)]
    out["midline"] = {
        "backs": len(mids),
        "rms_mm": _rms([m["rms_mm"] for m in mids]),
        "p95_backs_mm": _p95([m["rms_mm"] for m in mids]),
        "max_mm": _max([m["max_abs_mm"] for m in mids]),
        "coverage_median": float(np.median([m["coverage"] for m in mids])) if mids else math.nan,
        "deviation_max_error_rms_mm": _rms(extreme),
        "deviation_max_error_max_mm": _max(extreme),
    }
    rots = [r["rotation"] for r in ok if r["rotation"]]
    out["rotation"] = {
        "backs": len(rots),
        "rms_deg": _rms([m["rms_deg"] for m in rots]),
        "p95_backs_deg": _p95([m["rms_deg"] for m in rots]),
        "max_error_rms_deg": _rms([m["max_error_deg"] for m in rots]),
    }
    straight = [r for r in ok if r["straight"]]
    out["straight"] = {
        "backs": len(straight),
        "deviation_max_mm": _max([r["midline"]["max_abs_mm"] for r in straight if r["midline"]]),
        "rotation_max_deg": _max([r["rotation"]["max_abs_deg"] for r in straight if r["rotation"]]),
        "deviation_param_mm": _max(_errors(straight, "lateral_deviation_max_mm")),
        "rotation_param_deg": _max(_errors(straight, "surface_rotation_max_deg")),
    }
    params: dict[str, Any] = {}
    names = list(ok[0]["parameters"]) if ok else []
    for name in names:
        errs = [
            r["parameters"][name]["value"] - r["parameters"][name]["truth"]
            for r in ok
            if r["parameters"][name]["value"] is not None
        ]
        params[name] = {
            "n": len(errs),
            "bias": float(np.mean(errs)) if errs else math.nan,
            "rms": _rms(errs),
            "p95": _p95(errs),
            # a signed maximum takes the sign of the larger extreme: it flips when both are
            # nearly equal, and one flip dominates the rms
            "sign_flips": sum(
                1
                for r in ok
                if name.endswith(("_max_mm", "_max_deg"))
                and not name.endswith(("pos_max_mm", "neg_max_mm", "pos_max_deg", "neg_max_deg"))
                and (p := r["parameters"][name])["value"] is not None
                and abs(p["truth"]) > 1.0
                and p["value"] * p["truth"] < 0.0
            ),
        }
    out["parameters"] = params
    out["unmatched_parameters"] = sorted({n for r in ok for n in r["unmatched_parameters"]})
    times = [r["analysis_ms"] for r in ok]
    out["analysis_ms_median"] = float(np.median(times)) if times else math.nan
    out["analysis_ms_p90"] = float(np.percentile(times, 90)) if times else math.nan
    return out


def summarise_repeats(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Standard deviation of every parameter over the repeats of each back."""
    ok = [r for r in rows if "error" not in r]
    by_back: dict[str, list[dict[str, Any]]] = {}
    for r in ok:
        by_back.setdefault(r["back"], []).append(r)
    names = list(ok[0]["parameters"]) if ok else []
    out: dict[str, Any] = {
        "backs": len(by_back),
        "repeats": max((len(v) for v in by_back.values()), default=0),
        "crashed": len(rows) - len(ok),
        "parameters": {},
        "landmarks": {},
    }
    for name in names:
        sds, truth_sds, found = [], [], 0
        for reps in by_back.values():
            values = [r["parameters"][name]["value"] for r in reps]
            values = [v for v in values if v is not None]
            found += len(values)
            if len(values) >= 2:
                sds.append(float(np.std(values, ddof=1)))
            truths = [r["parameters"][name]["truth"] for r in reps]
            if len(truths) >= 2:
                truth_sds.append(float(np.std(truths, ddof=1)))
        out["parameters"][name] = {
            "found": found,
            # the pooled within-back SD (root mean of the variances): the standard error of
            # measurement behind a smallest detectable change (Weir, J Strength Cond Res 2005)
            "sd_pooled": float(np.sqrt(np.mean(np.square(sds)))) if sds else math.nan,
            "sd_median": float(np.median(sds)) if sds else math.nan,
            "sd_max": float(np.max(sds)) if sds else math.nan,
            "truth_sd_median": float(np.median(truth_sds)) if truth_sds else math.nan,
        }
    for name in LANDMARK_NAMES:
        sds = []
        for reps in by_back.values():
            errs = np.array(
                [r["landmarks"][name]["error"] for r in reps if r["landmarks"][name]["found"]]
            )
            if len(errs) >= 2:
                # spread of the error vector: the detection's own scatter, sway removed
                sds.append(float(np.sqrt(np.sum(np.var(errs, axis=0, ddof=1)))))
        out["landmarks"][name] = {
            "sd_median_mm": float(np.median(sds)) if sds else math.nan,
            "sd_max_mm": float(np.max(sds)) if sds else math.nan,
        }
    return out


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The whole summary: per set, repeatability."""
    return {
        "tuning": summarise_set([r for r in rows if r["set"] == "tuning"]),
        "held-out": summarise_set([r for r in rows if r["set"] == "held-out"]),
        "repeatability": summarise_repeats([r for r in rows if r["set"] == "repeat"]),
    }


def time_analysis(repeat: int) -> dict[str, Any]:
    """Median and best time (ms) of the analysis stage alone on the preset backs, one thread."""
    from rasterserver.pipeline import run_chain
    from rasterserver.simulator.back import make_back
    from rasterserver.simulator.render import render

    station, context = _station()
    out = {}
    for name in PRESET_NAMES:
        scene = make_back(back_params(name))
        image = render(scene, station, settings=render_settings(name), seed=1).image
        surface = run_chain(image, context=context, until="surface")["surface"]
        times = []
        for _ in range(repeat):
            durations: dict[str, float] = {}
            run_chain(surface, context=context, until="analysis", durations=durations)
            times.append(1e3 * durations["analysis"])
        out[name] = {"median_ms": float(np.median(times)), "best_ms": float(np.min(times))}
    return out


# ------------------------------------------------------------------------------ report


def _f(value: Any, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return f"{value:.{digits}f}"


def markdown(summary: dict[str, Any], meta: dict[str, Any]) -> str:
    """The BENCHMARKS.md section."""
    tun, held, rep = summary["tuning"], summary["held-out"], summary["repeatability"]
    lines = [
        "`benchmarks/analysis.py` renders simulated backs with the default station (604 x 576, "
        "varied light, blur and sensor noise), reconstructs the smoothed surface "
        '(`run_chain(..., until="surface")`), runs the installed analysis stage '
        f"(`{meta.get('plugin', 'analysis')}`) and scores it against the simulator's truth "
        "(`rasterserver.simulator.back_truth.truth`, definitions in `docs/simulator_truth.md`). "
        "Tuning set: "
        + ("presets normal, moderate, severe and " if meta.get("presets", True) else "")
        + f"`random_back` seeds {meta['tuning_seeds']}; "
        f"held-out set: seeds {meta['held_out_seeds']} (never looked at while tuning). "
        "Random backs also lean sideways (σ 1.5°) and turn (σ 2°). "
        f"Landmark errors are 3-D, over true landmarks at least {EDGE_PX:.0f} px inside the "
        "image; midline errors are frontal (X) distances to the true vertebral-body centres at "
        "the same height; rotation errors are against the true surface rotation at the same "
        "height.",
        "",
        f"Reproduce: `{meta['command']}`.",
        "",
        f"Machine: {meta['machine']}. Load average {meta['load_before']:.1f} before, "
        f"{meta['load_after']:.1f} after; {meta['wall_min']:.0f} min wall time on "
        f"{meta['workers']} processes.",
        "",
        "**Accuracy against the truth**",
        "",
        "| figure | target | tuning | held-out |",
        "|---|---:|---:|---:|",
        f"| backs (crashed, empty analysis) | | {tun['backs']} ({tun['crashed']}, {tun['empty']}) "
        f"| {held['backs']} ({held['crashed']}, {held['empty']}) |",
    ]
    for name in ("VP", "DL", "DR", "DM", "SP"):
        a, b = tun["landmarks"][name], held["landmarks"][name]
        target = "≤ 2" if name in ("VP", "DL", "DR") else ""
        lines.append(
            f"| {name} rms / p95 (mm), found in view | {target} | {_f(a['rms_mm'])} / "
            f"{_f(a['p95_mm'])}, {a['found_in_view']}/{a['in_view']} | {_f(b['rms_mm'])} / "
            f"{_f(b['p95_mm'])}, {b['found_in_view']}/{b['in_view']} |"
        )
    rows = [
        ("VP, DL, DR together rms (mm)", "≤ 2", "vp_dl_dr_rms_mm", None),
        ("midline lateral deviation rms (mm)", "≤ 2", "midline", "rms_mm"),
        ("midline lateral deviation, worst point (mm)", "", "midline", "max_mm"),
        (
            "largest lateral deviation (+max and −max), error rms (mm)",
            "≤ 2",
            "midline",
            "deviation_max_error_rms_mm",
        ),
        (
            "largest lateral deviation (+max and −max), worst error (mm)",
            "≤ 2",
            "midline",
            "deviation_max_error_max_mm",
        ),
        ("midline coverage of VP–DM (median)", "", "midline", "coverage_median"),
        ("surface rotation rms (deg)", "≤ 1.5", "rotation", "rms_deg"),
        (
            "straight backs: worst error of `lateral_deviation_max_mm` (mm)",
            "≤ 1",
            "straight",
            "deviation_param_mm",
        ),
        (
            "straight backs: worst error of `surface_rotation_max_deg` (deg)",
            "≤ 1",
            "straight",
            "rotation_param_deg",
        ),
        ("straight backs: worst midline point error (mm)", "", "straight", "deviation_max_mm"),
        ("straight backs: worst rotation point error (deg)", "", "straight", "rotation_max_deg"),
        ("analysis time in the workers, median / p90 (ms)", "≤ 100", None, None),
    ]
    for label, target, key, sub in rows:
        if key is None:
            va = f"{_f(tun['analysis_ms_median'], 1)} / {_f(tun['analysis_ms_p90'], 1)}"
            vb = f"{_f(held['analysis_ms_median'], 1)} / {_f(held['analysis_ms_p90'], 1)}"
        elif sub is None:
            va, vb = _f(tun[key]), _f(held[key])
        else:
            va, vb = _f(tun[key][sub]), _f(held[key][sub])
        lines.append(f"| {label} | {target} | {va} | {vb} |")
    lines += [
        "",
        "**Landmarks refused** (reason: count; *in view* means the true landmark lies at least "
        f"{EDGE_PX:.0f} px inside the image, where a refusal is a miss)",
        "",
        "SP lies near or below the bottom of the 604 mm field of view for long trunks (the "
        "simulator frames VP–DM, not the buttocks), so most of its refusals are expected.",
        "",
        "| landmark | set | in view: found / refused | refused in view, why "
        "| at the edge or outside: found / refused | why |",
        "|---|---|---:|---|---:|---|",
    ]
    for name in LANDMARK_NAMES:
        for label, s in (("tuning", tun), ("held-out", held)):
            e = s["landmarks"][name]
            elsewhere = e["at_edge"] + e["out_of_view"]
            found_else = e["found_at_edge"] + e["found_out_of_view"]
            why_in = "; ".join(f"{k}: {v}" for k, v in e["refusals_in_view"].items()) or "–"
            why_else = "; ".join(f"{k}: {v}" for k, v in e["refusals_elsewhere"].items()) or "–"
            lines.append(
                f"| {name} | {label} | {e['found_in_view']} / {e['in_view'] - e['found_in_view']} "
                f"| {why_in} | {found_else} / {elsewhere - found_else} | {why_else} |"
            )
    lines += [
        "",
        "**Parameters against the truth** (error = analysis − truth; n = backs where the analysis "
        "gave a value)",
        "",
        "| parameter | n | bias | rms | p95 | held-out n | bias | rms | p95 |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, a in tun["parameters"].items():
        b = held["parameters"].get(name, {})
        if not a["n"] and not b.get("n"):
            continue
        lines.append(
            f"| `{name}` | {a['n']} | {_f(a['bias'])} | {_f(a['rms'])} | {_f(a['p95'])} "
            f"| {b.get('n', 0)} | {_f(b.get('bias'))} | {_f(b.get('rms'))} | {_f(b.get('p95'))} |"
        )
    flips = [
        f"`{n}` {a.get('sign_flips', 0)} / {held['parameters'].get(n, {}).get('sign_flips', 0)}"
        for n, a in tun["parameters"].items()
        if a.get("sign_flips") or held["parameters"].get(n, {}).get("sign_flips")
    ]
    if flips:
        lines += [
            "",
            "Signed maxima take the sign of the larger extreme, so where both extremes are nearly "
            "equal (a double curve) a small error flips the sign, and one flip dominates the rms; "
            "backs with a flipped sign (tuning / held-out): " + ", ".join(flips) + ". The "
            "`*_pos_max_*` and `*_neg_max_*` values do not flip.",
        ]
    missing = [n for n, a in tun["parameters"].items() if not a["n"]]
    if missing:
        lines += ["", "Truth parameters the analysis did not report: " + ", ".join(missing) + "."]
    if tun["unmatched_parameters"]:
        lines += [
            "",
            "Analysis parameters without a truth: "
            + ", ".join(f"`{n}`" for n in tun["unmatched_parameters"])
            + ".",
        ]
    lines += [
        "",
        f"**Repeatability** ({rep['backs']} tuning backs, {rep['repeats']} acquisitions each: "
        "independent noise, posture sway up to ±5 mm and ±1° about each axis). SD = standard "
        "deviation over the acquisitions of one back, median and largest over the backs; "
        "*truth SD* is what the sway itself changes in the true value: where SD and truth SD "
        "agree, the spread is the patient's posture, which the analysis follows, not "
        "measurement noise; a change between two visits is detectable when it exceeds about "
        "2.8 SD (95 % for the difference of two acquisitions). The landmark SD is that of the "
        "error vector (the sway removed).",
        "",
        "| parameter | SD median | SD max | truth SD median |",
        "|---|---:|---:|---:|",
    ]
    for name, p in rep["parameters"].items():
        if p["found"]:
            lines.append(
                f"| `{name}` | {_f(p['sd_median'])} | {_f(p['sd_max'])} "
                f"| {_f(p['truth_sd_median'])} |"
            )
    lines += ["", "| landmark (error vector, mm) | SD median | SD max |", "|---|---:|---:|"]
    for name, p in rep["landmarks"].items():
        lines.append(f"| {name} | {_f(p['sd_median_mm'])} | {_f(p['sd_max_mm'])} |")
    if meta.get("timing"):
        lines += [
            "",
            "**Time of the analysis stage alone** (one thread, sequential, no other benchmark "
            f"process; {meta['timing_repeat']} runs per back; ms). The times in the workers "
            "above ran two processes beside other jobs on the shared machine.",
            "",
            "| back | median | best |",
            "|---|---:|---:|",
        ]
        for name, t in meta["timing"].items():
            lines.append(f"| {name} | {_f(t['median_ms'], 1)} | {_f(t['best_ms'], 1)} |")
    # Prose wrapped like the rest of BENCHMARKS.md; table rows stay whole.
    wrapped = [
        line
        if line.startswith("|") or len(line) <= 95
        else textwrap.fill(line, 95, break_long_words=False, break_on_hyphens=False)
        for line in lines
    ]
    return "\n".join(wrapped) + "\n"


# ------------------------------------------------------------------------------ main


def _parse_seeds(text: str) -> list[int]:
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            lo, hi = (int(x) for x in part.split("-", 1))
            if hi < lo:
                raise argparse.ArgumentTypeError(f"empty seed range {part!r}")
            seeds += range(lo, hi + 1)
        else:
            seeds.append(int(part))
    if any(s < 0 for s in seeds):
        raise argparse.ArgumentTypeError("seeds must be >= 0")
    return seeds


def _seed_ranges(seeds: list[int]) -> str:
    if not seeds:
        return "none"
    seeds = sorted(seeds)
    parts, start, prev = [], seeds[0], seeds[0]
    for s in [*seeds[1:], None]:
        if s is not None and s == prev + 1:
            prev = s
            continue
        parts.append(f"{start}–{prev}" if prev > start else f"{start}")
        if s is not None:
            start = prev = s
    return ", ".join(parts)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=100, help="random backs per set (default 100)")
    ap.add_argument(
        "--seeds",
        type=_parse_seeds,
        default=None,
        help="random_back seeds instead of the two sets, e.g. 0-9,1000-1004 (>= 1000: held-out;"
        " no presets)",
    )
    ap.add_argument("--repeat-backs", type=int, default=10, help="backs for repeatability")
    ap.add_argument("--repeats", type=int, default=10, help="acquisitions per repeated back")
    ap.add_argument("--timing-repeat", type=int, default=20, help="runs per back, timing pass")
    ap.add_argument("--quick", action="store_true", help="4 backs per set, 2 x 3 repeats")
    ap.add_argument(
        "--params",
        default=None,
        help='stage parameters of the chain, JSON: {"numbers": {...}, "analysis": {...}} '
        "(to compare a plugin's settings in one run)",
    )
    ap.add_argument("--workers", type=int, default=2, choices=(1, 2))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/analysis.json"))
    ap.add_argument("--summary", type=Path, default=None, help="only summarise this run")
    add_write_options(ap)
    args = ap.parse_args(argv)
    if args.count < 0 or args.repeat_backs < 0 or args.repeats < 0:
        ap.error("counts must be >= 0")
    if args.quick:
        args.count, args.repeat_backs, args.repeats, args.timing_repeat = 4, 2, 3, 5
    out = args.summary or args.out
    lines_path = out.with_suffix(".jsonl")
    meta_path = out.with_suffix(".meta.json")

    if args.summary is None:
        out.parent.mkdir(parents=True, exist_ok=True)
        todo_all = tasks(args.count, args.seeds, args.repeat_backs, args.repeats)
        code = analysis_code()
        done = set()
        if lines_path.exists():
            rows = [json.loads(x) for x in lines_path.read_text().splitlines() if x.strip()]
            done = {_key(r) for r in rows if r.get("code") == code}
        todo = [t for t in todo_all if _key(t) not in done]
        print(f"{len(done)} acquisitions done, {len(todo)} to go", flush=True)
        load_before = os.getloadavg()[0]
        start = time.time()
        if todo:
            with (
                # workers live the whole run: they load the analysis once, so it cannot change
                # half-way through (rows of other code are left out below anyway)
                mp.get_context("spawn").Pool(
                    args.workers,
                    initializer=_init,
                    initargs=(json.loads(args.params) if args.params else None,),
                ) as pool,
                lines_path.open("a") as fh,
            ):
                for i, res in enumerate(pool.imap_unordered(_safe, todo, chunksize=1), 1):
                    fh.write(json.dumps(res) + "\n")
                    fh.flush()
                    if i % 10 == 0 or "error" in res or i == len(todo):
                        rate = (time.time() - start) / i
                        print(
                            f"{i}/{len(todo)} {_key(res)} "
                            f"{res.get('error') or res.get('reason') or 'ok'} "
                            f"{rate:.1f} s/acquisition",
                            flush=True,
                        )
        wall = (time.time() - start) / 60.0
        print("timing the analysis alone ...", flush=True)
        timing = time_analysis(args.timing_repeat) if args.timing_repeat else {}
        keys = {_key(t) for t in todo_all}
        seeds_used = sorted(
            {
                int(k.split(":")[1].split("-")[1])
                for k in keys
                if k.split(":")[1].startswith("random") and not k.startswith("repeat")
            }
        )

        command = (
            "python benchmarks/analysis.py"
            + (" --quick" if args.quick else "" if args.seeds else f" --count {args.count}")
            + f" --out {out}"
            + (f" --params '{args.params}'" if args.params else "")
        )
        if args.seeds is not None:
            command += " --seeds " + ",".join(str(s) for s in args.seeds)
        meta = {
            "machine": machine(),
            "command": command,
            "tuning_seeds": _seed_ranges([s for s in seeds_used if s < HELD_OUT_FIRST_SEED]),
            "held_out_seeds": _seed_ranges([s for s in seeds_used if s >= HELD_OUT_FIRST_SEED]),
            "workers": args.workers,
            "load_before": load_before,
            "load_after": os.getloadavg()[0],
            "wall_min": wall,
            "timing": timing,
            "timing_repeat": args.timing_repeat,
            "plugin": code,
            "presets": args.seeds is None,
            "keys": sorted(keys),
        }
        meta_path.write_text(json.dumps(meta, indent=2))
    meta = json.loads(meta_path.read_text())
    keys = set(meta.pop("keys", []))
    all_rows = [json.loads(x) for x in lines_path.read_text().splitlines() if x.strip()]
    all_rows = [r for r in all_rows if not keys or _key(r) in keys]
    rows = [r for r in all_rows if r.get("code") == meta["plugin"]]
    stale = [r for r in all_rows if r.get("code") != meta["plugin"]]
    if stale:
        print(f"left out {len(stale)} rows made by other analysis code", flush=True)
    summary = summarise(rows)
    out.write_text(json.dumps({"meta": meta, **summary}, indent=2, default=float))
    report = markdown(summary, meta)
    out.with_suffix(".md").write_text(report)
    print(report)
    if args.write:
        write_subsection(TITLE, subsection_heading(args.heading, __file__), report)
        print(f"wrote the section {TITLE!r} of BENCHMARKS.md", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
