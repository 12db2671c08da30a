"""Numbering and peak location on what a clinic's camera sees (head, hair, arms, clothing).

Every scene is :func:`rasterserver.simulator.body.random_body` (a random back with head and
hair, arms close / away / hands on hips, a waistband in three scenes of four, posture sway),
seen by :func:`rasterserver.simulator.body.clinic_station` (random distance and base) through
one of four diapositive codes (``seed % 4``: the default window-9 code and the clinic rasters
``mseq7`` (window-7 m-sequence, distance 1), ``w8-1to2`` (window 8, distance 1, light:heavy
1:2), ``w9-45to55`` (window 9, distance 2, 45:55)), rendered with randomly varied light,
noise and blur (as :mod:`benchmarks.numbering_backs`). Stages 1-4 run with their defaults.

Truth: a peak's true number is the simulator's exact line centre within 1.5 px in its
column (the counting of ``numbering_backs.py``: ``_truth_numbers``), and the per-pixel line
number of the rendering at the peak's pixel must agree (otherwise the peak has no truth).
Per scene (one JSON line each, resumable):

* ``wrong_peaks``: numbered peaks whose number is not their true one; ``wrong_lines``;
  ``wrong_on_back``: those of them on the back proper (the trunk at or below the vertebra
  prominens, the region the clinical answer reads) rather than on a cloth, arm, head or
  neck;
* ``trunk_crossings``/``trunk_covered``: exact line-centre crossings on the trunk (the lit
  skin of neck, back and buttocks) and those carrying a peak with the correct number;
* ``headarm_peaks``/``headarm_unnumbered``: peaks on true lines of the head and arms and how
  many of them are left unnumbered;
* peak location: squared-error sums of the reconstructed (numbered, true) peaks and of all
  matched peaks, and of a generic local-maximum + 3-point Gaussian detector on the same
  frame; both detectors timed on the same frame; ``dropped_peaks``: peaks the detector
  dropped as untrustworthy (``Peaks.dropped``);
* ``ms``: per-stage times (peaks, generic detector, lines, order, numbers).

``--cache DIR`` keeps the rendered frames (npz) and reuses them: tuning runs then cost the
stages only (rendering is ~95 % of a scene's time).

Usage::

    python benchmarks/real_bodies.py --first-seed 0 --scenes 200 \
        --out benchmarks/out/bodies-tune.jsonl
    python benchmarks/real_bodies.py --summary benchmarks/out/bodies-tune.jsonl

``--code mseq7`` keeps only the range's scenes seen through one diapositive code (a tuning
set of one raster); ``--raster mseq8-35to65`` sees every scene of the range through that
built-in raster instead (the raster held out from tuning,
:data:`rasterserver.raster.HELD_OUT_RASTERS`). ``--posture close`` keeps only the scenes
whose body holds its arms so (with ``--code mseq7``: the stress set of section (35) of
BENCHMARKS.md, where an arm hides one trunk line and its own lines take the hidden line's
rows).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import multiprocessing as mp  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

CODES = ("default", "mseq7", "w8-1to2", "w9-45to55")
TUNING = (0, 200)  # seeds 0-199
HELD_OUT = (5000, 6200)  # seeds 5000-6199


def _sibling(name: str) -> Any:
    return importlib.import_module(name)  # a script beside this one; once per process


def generic_peaks(image: np.ndarray, *, min_height: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """A generic detector: local maxima per column refined by a 3-point Gaussian fit.

    A pixel is a peak when it exceeds both vertical neighbours (ties to the lower one) and
    the smaller of the column's minima within 4 px either side by ``min_height``; the row is
    the vertex of the parabola through the logarithms of the three values.

    Returns
    -------
    col, row : numpy.ndarray
        Sorted by column, then row.
    """
    img = np.asarray(image, dtype=np.float32).T  # columns as rows
    a, b, c = img[:, :-2], img[:, 1:-1], img[:, 2:]
    from scipy.ndimage import minimum_filter1d

    low = minimum_filter1d(img, 9, axis=1)[:, 1:-1]
    is_max = (b > a) & (b >= c) & (b - low >= min_height)
    cc, rr = np.nonzero(is_max)
    la = np.log(np.maximum(a[cc, rr], 0.5))
    lb = np.log(np.maximum(b[cc, rr], 0.5))
    lc = np.log(np.maximum(c[cc, rr], 0.5))
    den = la - 2.0 * lb + lc
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den < 0, 0.5 * (la - lc) / den, 0.0)
    return cc.astype(np.int32), rr + 1.0 + np.clip(off, -0.5, 0.5)


def _match(
    col: np.ndarray, row: np.ndarray, lr: Any, tol: float = 1.5
) -> tuple[np.ndarray, np.ndarray]:
    """Index into the line rows of the nearest exact crossing in the peak's column (-1)."""
    gc, gr = lr.column.astype(np.int64), lr.row
    order = np.lexsort((gr, gc))
    kg = gc[order] * 1e5 + gr[order]
    kp = col.astype(np.int64) * 1e5 + row
    if kg.size == 0 or kp.size == 0:
        return np.full(kp.size, -1, np.int64), np.full(kp.size, np.inf)
    last = kg.size - 1
    j = np.clip(np.searchsorted(kg, kp), 1, max(last, 1))
    j0, j1 = np.clip(j - 1, 0, last), np.clip(j, 0, last)
    e0, e1 = np.abs(kg[j0] - kp), np.abs(kg[j1] - kp)
    jj = np.where(e0 < e1, j0, j1)
    err = np.minimum(e0, e1)
    return np.where(err < tol, order[jj], -1), np.where(err < tol, kp - kg[jj], np.inf)


@dataclass
class Frame:
    """One rendered scene with the truth the scoring needs (small enough to cache)."""

    seed: int
    code: str
    posture: str
    waistband: bool
    hair_albedo: float
    image: np.ndarray
    line_number: np.ndarray  # (H, W) per-pixel true line number
    object_index: np.ndarray  # (H, W) per-pixel object
    names: list[str]
    lr_column: np.ndarray
    lr_row: np.ndarray
    lr_number: np.ndarray
    lr_object: np.ndarray
    lr_on_back: np.ndarray  # crossing on the trunk at or below the vertebra prominens
    render_s: float

    @property
    def line_rows(self) -> Any:
        from rasterserver.simulator.ground_truth import LineRows

        return LineRows(self.lr_column, self.lr_number, self.lr_row, self.lr_object)

    def save(self, path: Path) -> None:
        """Write the frame to ``path`` (npz), whole or not at all."""
        arrays = {k: v for k, v in self.__dict__.items() if isinstance(v, np.ndarray)}
        meta = {k: v for k, v in self.__dict__.items() if not isinstance(v, np.ndarray)}
        # a file of this process's own: two runs sharing a frame folder may render the same
        # scene at once, and writing one temporary file together corrupted the frame
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
        np.savez_compressed(tmp, meta=np.array(json.dumps(meta)), **arrays)
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> Frame:
        """Read a frame written by :meth:`save`."""
        with np.load(path) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in z.files if k != "meta"}
        return cls(**meta, **arrays)


def render_scene(seed: int, raster: str | None = None) -> Frame:
    """Render scene ``seed`` (body, station and code from the seed; ``raster``, a built-in
    raster's name, instead of the seed's code) with its truth."""
    from rasterserver.simulator.body import clinic_station, make_body, random_body
    from rasterserver.simulator.render import render

    backs = _sibling("numbering_backs")
    code = raster or CODES[seed % len(CODES)]
    params = random_body(seed)
    station = clinic_station(seed, code)
    t0 = time.perf_counter()
    scene = make_body(params)
    rendering = render(scene, station, settings=backs._settings(seed).replace(threads=1), seed=seed)
    t_render = time.perf_counter() - t0
    lr = rendering.line_rows
    names = list(rendering.object_names)
    h = rendering.line_number.shape[0]
    trunk = names.index("trunk") if "trunk" in names else -99
    # the back proper: trunk crossings at or below the vertebra prominens (the neck above it
    # is often under hair and in the head's shadow)
    vp_y = float(scene.landmarks["vertebra_prominens"][1])
    rr = np.clip(np.rint(lr.row).astype(np.int64), 0, h - 1)
    on_back = (lr.object_index == trunk) & (rendering.points[rr, lr.column, 1] >= vp_y)
    return Frame(
        seed=seed,
        code=code,
        posture=str(params.arm_posture),
        waistband=params.waistband is not None,
        hair_albedo=float(params.hair_albedo),
        image=rendering.image,
        line_number=rendering.line_number,
        object_index=rendering.object_index,
        names=names,
        lr_column=lr.column,
        lr_row=lr.row,
        lr_number=lr.number,
        lr_object=lr.object_index,
        lr_on_back=on_back,
        render_s=round(t_render, 3),
    )


def peak_truth(frame: Frame, result: Any) -> tuple[np.ndarray, np.ndarray]:
    """Each peak's true line number (-1: none) and the object at its pixel.

    The true number is the simulator's exact line centre within 1.5 px in the peak's column
    (``numbering_backs._truth_numbers``); the per-pixel line number of the rendering at the
    peak's pixel must agree, otherwise the peak is off its line's pixels and has no truth.
    """
    truth = _sibling("numbering_backs")._truth_numbers(result.col, result.row, frame.line_rows)
    h = frame.line_number.shape[0]
    r_pix = np.clip(np.rint(result.row).astype(np.int64), 0, h - 1)
    pixel = frame.line_number[r_pix, result.col]
    return np.where(pixel == truth, truth, -1), frame.object_index[r_pix, result.col]


def covered_crossings(
    frame: Frame, result: Any, truth: np.ndarray, idx: np.ndarray | None = None
) -> np.ndarray:
    """Per exact line crossing of ``frame``, whether a peak carries its correct number
    (``idx``: each peak's crossing from :func:`_match`, computed when not given)."""
    if idx is None:
        idx, _ = _match(result.col, result.row, frame.line_rows)
    good = (result.number >= 0) & (truth >= 0) & (idx >= 0) & (result.number == truth)
    covered = np.zeros(len(frame.line_rows), dtype=bool)
    covered[idx[good]] = True
    return covered


def ordered_lines(
    frame: Frame, params: dict[str, dict[str, Any]] | None = None
) -> tuple[Any, Any, dict[str, float]]:
    """Stages 1-3 on ``frame`` (``params``: per-stage parameters, ``{"peaks": {...}}``):
    the ordered lines, the stage context of the scene's station and raster (for the
    numbering), and each stage's time (ms)."""
    from rasterserver_plugins.line_search import HierarchicalLineSearch
    from rasterserver_plugins.line_sequence import HierarchicalLineOrder
    from rasterserver_plugins.peak_detection import FirstMomentPeaks

    from rasterserver.records import Image
    from rasterserver.simulator.body import clinic_station
    from rasterserver.stage import StageContext, run_stage

    params = params or {}
    station = clinic_station(frame.seed, frame.code)
    ctx = StageContext(calibration=station, raster=station.raster_definition)
    ms: dict[str, float] = {}
    data: Any = Image(frame.image)
    for name, stage in (
        ("peaks", FirstMomentPeaks),
        ("lines", HierarchicalLineSearch),
        ("order", HierarchicalLineOrder),
    ):
        t = time.perf_counter()
        data = run_stage(stage, data, params=params.get(name))
        ms[name] = round(1e3 * (time.perf_counter() - t), 3)
    return data, ctx, ms


def run_stages(
    frame: Frame, params: dict[str, dict[str, Any]] | None = None
) -> tuple[Any, dict[str, float]]:
    """Stages 1-4 on ``frame`` with its station and raster (``params``: per-stage parameters,
    ``{"peaks": {...}, "numbers": {...}}``): the numbered lines and each stage's time (ms)."""
    from rasterserver_plugins.line_numbering import CodeWindowNumbering

    from rasterserver.stage import run_stage

    ordered, ctx, ms = ordered_lines(frame, params)
    t = time.perf_counter()
    numbers = (params or {}).get("numbers")
    result = run_stage(CodeWindowNumbering, ordered, params=numbers, context=ctx)
    ms["numbers"] = round(1e3 * (time.perf_counter() - t), 3)
    return result, ms


def wrong_peaks(number: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per peak: numbered, with a true number (:func:`peak_truth`), and not that one."""
    return (number >= 0) & (truth >= 0) & (number != truth)


def on_the_back(peaks: np.ndarray, crossing: np.ndarray, on_back: np.ndarray) -> np.ndarray:
    """Per peak: selected by ``peaks`` and matched to a crossing of the back proper.

    Parameters
    ----------
    peaks : numpy.ndarray
        Bool per peak (e.g. :func:`wrong_peaks`).
    crossing : numpy.ndarray
        Each peak's exact crossing (:func:`_match`; -1: none).
    on_back : numpy.ndarray
        Bool per crossing: on the trunk at or below the vertebra prominens
        (``Frame.lr_on_back``), the region the clinical answer reads.

    Returns
    -------
    numpy.ndarray
        Bool per peak.
    """
    crossing = np.asarray(crossing)
    if on_back.size == 0:
        return np.zeros(crossing.size, dtype=bool)
    return np.asarray(peaks, dtype=bool) & (crossing >= 0) & on_back[np.maximum(crossing, 0)]


def score_frame(frame: Frame) -> dict[str, Any]:
    """Run stages 1-4 on ``frame`` and score them against its truth."""
    result, ms = run_stages(frame, _PARAMS)
    image = frame.image
    t = time.perf_counter()
    g_col, g_row = generic_peaks(image)
    t_generic = time.perf_counter() - t

    lr = frame.line_rows
    names = frame.names
    truth, obj = peak_truth(frame, result)
    on_line = truth >= 0
    numbered = result.number >= 0
    wrong = wrong_peaks(result.number, truth)
    numbered_off = numbered & ~on_line
    wrong_lines = 0
    for line in np.unique(result.line_id[wrong]):
        sel = (result.line_id == line) & on_line
        maj = np.bincount(truth[sel]).argmax() if np.any(sel) else -1
        if result.line_number[line] >= 0 and maj != result.line_number[line]:
            wrong_lines += 1
    idx, err = _match(result.col, result.row, lr)
    trunk = names.index("trunk") if "trunk" in names else -99
    on_trunk = lr.object_index == trunk
    on_back = frame.lr_on_back
    covered = covered_crossings(frame, result, truth, idx)
    headarm = np.isin(
        obj, [names.index(n) for n in ("head", "left-arm", "right-arm") if n in names]
    )
    rec = numbered & on_line & (result.number == truth) & np.isfinite(err)
    allm = on_line & np.isfinite(err)
    _, g_err = _match(g_col, g_row, lr)
    g_ok = np.isfinite(g_err)
    by_obj = {}
    for k, n in enumerate(names):
        sel = rec & (obj == k)
        by_obj[n] = [int(sel.sum()), float(np.sum(err[sel] ** 2))]
    dropped = int(result.dropped or 0)
    return {
        "seed": frame.seed,
        "code": frame.code,
        "posture": frame.posture,
        "waistband": frame.waistband,
        "hair_albedo": frame.hair_albedo,
        "peaks": int(result.n_peaks),
        "dropped_peaks": dropped,
        "true_peaks": int(on_line.sum()),
        "numbered_peaks": int(numbered.sum()),
        "wrong_peaks": int(wrong.sum()),
        "wrong_on_back": int(on_the_back(wrong, idx, on_back).sum()),
        "wrong_lines": wrong_lines,
        "wrong_objects": sorted({names[int(o)] for o in obj[wrong] if o >= 0}),
        "numbered_off_truth": int(numbered_off.sum()),
        "trunk_crossings": int(on_trunk.sum()),
        "trunk_covered": int((covered & on_trunk).sum()),
        "back_crossings": int(on_back.sum()),
        "back_covered": int((covered & on_back).sum()),
        "headarm_peaks": int((headarm & on_line).sum()),
        "headarm_unnumbered": int((headarm & on_line & ~numbered).sum()),
        "rec_n": int(rec.sum()),
        "rec_sse": float(np.sum(err[rec] ** 2)),
        "rec_max": float(np.max(np.abs(err[rec]), initial=0.0)),
        "all_n": int(allm.sum()),
        "all_sse": float(np.sum(err[allm] ** 2)),
        "generic_n": int(g_ok.sum()),
        "generic_sse": float(np.sum(g_err[g_ok] ** 2)),
        "generic_peaks": int(g_col.size),
        "rec_by_object": by_obj,
        "reason": result.reason[:400],
        "ms": {**ms, "generic": round(1e3 * t_generic, 3)},
        "render_s": frame.render_s,
    }


_CACHE: Path | None = None
# a built-in raster every scene is seen through instead of the seed's code (``--raster``)
_RASTER: str | None = None
# per-stage parameters for tuning runs (``--params``): {"peaks": {...}, "numbers": {...}}
_PARAMS: dict[str, dict[str, Any]] = {}


def cached_frame(seed: int, raster: str | None = None, cache: Path | None = None) -> Frame:
    """Scene ``seed`` (through ``raster``) read from the frame folder ``cache``, or rendered
    and, with a folder, kept there (``scene-<seed>[-<raster>].npz``)."""
    if cache is None:
        return render_scene(seed, raster)
    path = cache / (f"scene-{seed}-{raster}.npz" if raster else f"scene-{seed}.npz")
    if path.exists():
        return Frame.load(path)
    frame = render_scene(seed, raster)
    frame.save(path)
    return frame


def run_scene(seed: int) -> dict[str, Any]:
    """Render scene ``seed`` (or read it from the frame cache), run stages 1-4, score."""
    return score_frame(cached_frame(seed, _RASTER, _CACHE))


def _init(
    cache: Path | None,
    params: dict[str, dict[str, Any]] | None = None,
    raster: str | None = None,
) -> None:
    global _CACHE, _PARAMS, _RASTER
    _CACHE = cache
    _PARAMS = params or {}
    _RASTER = raster


def _safe(seed: int) -> dict[str, Any]:
    try:
        return run_scene(seed)
    except Exception as exc:  # a crash is a result too: count it, keep going
        import traceback

        return {
            "seed": seed,
            "error": f"{type(exc).__name__}: {exc}",
            "tb": traceback.format_exc()[-800:],
        }


def summary(path: Path) -> dict[str, Any]:
    """Totals over the JSON lines in ``path``."""
    rows = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    ok = [r for r in rows if "error" not in r]

    def tot(key: str, sel: list[dict[str, Any]] = ok) -> float:
        return float(sum(r[key] for r in sel))

    def group(sel: list[dict[str, Any]]) -> dict[str, Any]:
        return {
            "scenes": len(sel),
            "wrong_peaks": int(tot("wrong_peaks", sel)),
            "wrong_on_back": sum(r.get("wrong_on_back", 0) for r in sel),
            "scenes_with_wrong": sum(1 for r in sel if r["wrong_peaks"]),
            "trunk_coverage": tot("trunk_covered", sel) / max(tot("trunk_crossings", sel), 1),
            "back_coverage": tot("back_covered", sel) / max(tot("back_crossings", sel), 1),
            "headarm_unnumbered": tot("headarm_unnumbered", sel)
            / max(tot("headarm_peaks", sel), 1),
            "rec_rms": (tot("rec_sse", sel) / max(tot("rec_n", sel), 1)) ** 0.5,
            "dropped_share": sum(r.get("dropped_peaks", 0) for r in sel)
            / max(sum(r.get("dropped_peaks", 0) + r["peaks"] for r in sel), 1),
        }

    codes = sorted({r["code"] for r in ok}, key=lambda c: (c not in CODES, c))
    per_code = {c: group([r for r in ok if r["code"] == c]) for c in codes}
    postures = sorted({r["posture"] for r in ok})
    per_posture = {p: group([r for r in ok if r["posture"] == p]) for p in postures}
    ms = np.array([[r["ms"]["peaks"], r["ms"]["generic"], r["ms"]["numbers"]] for r in ok])
    stages = [r["ms"] for r in ok if "lines" in r["ms"]]
    ms_stages = (
        np.median([[m[k] for k in ("peaks", "lines", "order", "numbers")] for m in stages], axis=0)
        .round(2)
        .tolist()
        if stages
        else []
    )
    dropped = float(sum(r.get("dropped_peaks", 0) for r in ok))
    return {
        "scenes": len(rows),
        "errors": len(rows) - len(ok),
        "error_seeds": [r["seed"] for r in rows if "error" in r][:20],
        "wrong_peaks": int(tot("wrong_peaks")),
        # of them on the back proper (rows written before this count was kept count 0)
        "wrong_on_back": sum(r.get("wrong_on_back", 0) for r in ok),
        "wrong_lines": int(tot("wrong_lines")),
        "scenes_with_wrong": sum(1 for r in ok if r["wrong_peaks"]),
        "wrong_seeds": [
            (r["seed"], r["code"], r["wrong_peaks"], r["wrong_objects"])
            for r in ok
            if r["wrong_peaks"]
        ][:40],
        "numbered_off_truth": int(tot("numbered_off_truth")),
        "trunk_coverage": tot("trunk_covered") / max(tot("trunk_crossings"), 1),
        "back_coverage": tot("back_covered") / max(tot("back_crossings"), 1),
        "back_coverage_p5": float(
            np.percentile([r["back_covered"] / max(r["back_crossings"], 1) for r in ok], 5)
        )
        if ok
        else 0.0,
        "trunk_coverage_p5": float(
            np.percentile([r["trunk_covered"] / max(r["trunk_crossings"], 1) for r in ok], 5)
        )
        if ok
        else 0.0,
        "headarm_unnumbered_share": tot("headarm_unnumbered") / max(tot("headarm_peaks"), 1),
        "rec_peaks": int(tot("rec_n")),
        "rec_rms": (tot("rec_sse") / max(tot("rec_n"), 1)) ** 0.5,
        "all_matched_rms": (tot("all_sse") / max(tot("all_n"), 1)) ** 0.5,
        "generic_rms": (tot("generic_sse") / max(tot("generic_n"), 1)) ** 0.5,
        "generic_matched": int(tot("generic_n")),
        "dropped_peaks": int(dropped),
        "dropped_share": dropped / max(dropped + tot("peaks"), 1),
        "numbered_share_of_true_peaks": (tot("numbered_peaks") - tot("numbered_off_truth"))
        / max(tot("true_peaks"), 1),
        "ms_median_peaks_generic_numbers": np.median(ms, axis=0).round(2).tolist() if ok else [],
        "ms_median_peaks_lines_order_numbers": ms_stages,
        "per_code": per_code,
        "per_posture": per_posture,
    }


def _raster_names() -> tuple[str, ...]:
    from rasterserver.raster import CLINIC_RASTERS, HELD_OUT_RASTERS, TUNING_RASTERS

    return ("default", *CLINIC_RASTERS, *HELD_OUT_RASTERS, *TUNING_RASTERS)


def _arm_postures() -> tuple[str, ...]:
    from rasterserver.simulator.body import ARM_POSTURES

    return ARM_POSTURES


def scene_choice(seeds: range, code: str | None = None, posture: str | None = None) -> list[int]:
    """The seeds of ``seeds`` whose scene is seen through ``code`` (``seed % 4``) and whose
    body holds its arms in ``posture`` (:func:`~rasterserver.simulator.body.random_body`'s
    draw; ``None``: any).

    Parameters
    ----------
    seeds : range
        The range of scene seeds.
    code : str, optional
        One of :data:`CODES`.
    posture : str, optional
        One of :data:`rasterserver.simulator.body.ARM_POSTURES`.

    Returns
    -------
    list of int
        The chosen seeds, in order.
    """
    from rasterserver.simulator.body import random_body

    return [
        s
        for s in seeds
        if (code is None or CODES[s % len(CODES)] == code)
        and (posture is None or random_body(s).arm_posture == posture)
    ]


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--scenes", type=int, default=200)
    ap.add_argument("--first-seed", type=int, default=TUNING[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/bodies-tune.jsonl"))
    ap.add_argument("--summary", type=Path, default=None, help="only summarise this file")
    ap.add_argument(
        "--code",
        choices=CODES,
        default=None,
        help="only the scenes of the range seen through this diapositive code (seed %% 4)",
    )
    ap.add_argument(
        "--posture",
        choices=_arm_postures(),
        default=None,
        help="only the scenes of the range whose body holds its arms so (a stress set of a "
        "rare case, e.g. arms close to the trunk)",
    )
    ap.add_argument(
        "--raster",
        choices=sorted(_raster_names()),
        default=None,
        help="see every scene through this built-in raster instead of the seed's code "
        "(a raster held out from tuning: mseq8-35to65; its tuning twin: mseq8b-35to65)",
    )
    ap.add_argument(
        "--params",
        default=None,
        help='stage parameters for tuning, JSON: {"peaks": {...}, "lines": {...}, ...}',
    )
    ap.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="folder of rendered frames: read when present, written when not (for tuning)",
    )
    args = ap.parse_args(argv)
    if args.raster is not None and args.code is not None:
        ap.error("--raster and --code exclude each other (--raster replaces every seed's code)")
    if args.summary is not None:
        print(json.dumps(summary(args.summary), indent=2))
        return 0
    chosen = scene_choice(
        range(args.first_seed, args.first_seed + args.scenes), args.code, args.posture
    )
    if not chosen:
        ap.error(
            f"no scene of seeds {args.first_seed}-{args.first_seed + args.scenes - 1} is seen "
            f"through {args.code or 'any code'} with arms {args.posture or 'in any posture'}"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.cache is not None:
        args.cache.mkdir(parents=True, exist_ok=True)
    from _resume import chain_stamp, done_seeds  # beside this script

    stamp = chain_stamp(json.loads(args.params) if args.params else None)
    if args.raster is not None:
        # rows seen through another raster must not be summarised with this run's
        stamp = {**stamp, "raster": args.raster}
    done = done_seeds(args.out, stamp)
    todo = [s for s in chosen if s not in done]
    print(f"{len(done)} scenes done, {len(todo)} to go", flush=True)
    start = time.time()
    with (
        mp.get_context("spawn").Pool(
            args.workers,
            initializer=_init,
            initargs=(
                args.cache,
                json.loads(args.params) if args.params else None,
                args.raster,
            ),
            maxtasksperchild=40,
        ) as pool,
        args.out.open("a") as fh,
    ):
        for i, res in enumerate(pool.imap_unordered(_safe, todo, chunksize=1), 1):
            fh.write(json.dumps({**res, "stamp": stamp}) + "\n")
            fh.flush()
            if i % 20 == 0 or res.get("wrong_peaks") or res.get("error"):
                rate = (time.time() - start) / i
                print(
                    f"{i}/{len(todo)} seed {res['seed']} wrong {res.get('wrong_peaks')} "
                    f"err {res.get('error')} {rate:.2f} s/scene",
                    flush=True,
                )
    print(json.dumps(summary(args.out), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
