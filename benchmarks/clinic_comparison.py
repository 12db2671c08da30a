"""Visits compared on what a clinic's camera sees: ``comparison.py``'s figures on clinic scenes.

``comparison.py`` measures the comparison of a patient's visits on backs without head, hair,
posed arms or clothing. At a clinic the patient comes back months later, dressed otherwise,
the arms held otherwise, the hair grown; the back is what must be compared. Per person (a
seed of :func:`rasterserver.simulator.body.random_body` with a curved back, seen through
:func:`~rasterserver.simulator.body.clinic_station` with the seed's diapositive code, the
same station and light at every visit) nine acquisitions with their own sensor noise, the
roles of ``comparison.py``:

* ``A`` the person as drawn; ``B`` re-posed by a known rigid motion (10-30 mm, 2-5°), in A's
  dress; ``C`` the main curve's axial rotation +3° in A's posture and dress; ``D`` A again;
* ``E``, ``H``, ``I``: **another visit**: a posture sway (±5 mm, ±1°) and the dress of
  another day (:func:`redress`: arm posture drawn again, the head held otherwise, the hair
  grown or cut, another waistband or none); ``F`` (lateral deviation +5 mm) and ``G``
  (rotation +3°) the same way.

Each acquisition is rendered twice with the same station, light and noise: ``body`` (the
whole clinic scene, :func:`~rasterserver.simulator.body.make_body`) and ``back`` (its back
alone, :func:`~rasterserver.simulator.back.make_back`, hanging arms, as ``comparison.py``
renders): the peer, in the same run. Both are scored by ``comparison.py``'s
:func:`score_back` and :func:`summarise` (registration of B against the true transform,
distance maps A→C against the true change, A→D and A→E with no change on the back,
trend flags on the noise-only pairs and on the progressions); and here, how often a
comparison was refused and why (a visit without a body frame cannot be registered: the
safe answer), and how many progressions got no answer at all. Every pair is compared with
the comparison's defaults, with version 1 (every vertex of the connected trunk: columns
``body_v1``, ``back_v1``), with version 3 (the distance map's hits through holes of the
other surface kept, and asymmetry version 2: ``body_v3``, ``back_v3``) and with the defaults
but asymmetry version 3 (the mirror fit on every trunk point: ``body_a3``, ``back_a3``) on
the same acquisitions.

Per person one JSON line (its scores for both kinds) is appended to ``--out`` once its 18
acquisitions are done; a rerun resumes, and rows of other analysis or comparison code are
refused. Sets: ``--first-seed`` (tuning from 0; held out from 40600, never looked at while
changing the code: 40600, 40700, 40800, 40850, 41500, 42400 and 43200 are scored in
BENCHMARKS.md; 40900-41499 and 42000-43105 hold ``clinic_analysis.py``'s held-out scenes
and checks; a fresh set starts at 43300).

Usage::

    python benchmarks/clinic_comparison.py --first-seed 0 --people 20 --out /tmp/cc.jsonl
    python benchmarks/clinic_comparison.py --summary /tmp/cc.jsonl
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import hashlib  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import multiprocessing as mp  # noqa: E402
import re  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _resume import read_rows  # noqa: E402

KINDS = ("body", "back")
#: The comparison's versions scored on the same acquisitions: the plugin's defaults,
#: version 1 (every vertex of the connected trunk compared), version 3 (the distance
#: map's hits through holes kept; asymmetry version 2) and the defaults with asymmetry
#: version 3 (the mirror fit on every trunk point).
VERSIONS = ("", "_v1", "_v3", "_a3")
#: Pairs whose registration is counted: the re-pose, the progression in A's dress, the same
#: posture, and one other visit (another dress).
PAIRS = ("B", "C", "D", "E")


def _bench(name: str) -> Any:
    return importlib.import_module(name)  # a script beside this one; once per process


def people(first: int, count: int) -> list[int]:
    """The first ``count`` seeds from ``first`` whose back has a curve (one to grow)."""
    from rasterserver.simulator.body import random_body

    out, seed = [], first
    while len(out) < count:
        if random_body(seed).back.curves:
            out.append(seed)
        seed += 1
    return out


def redress(body: Any, seed: int) -> Any:
    """The same person on another day: arms, head, hair and clothing drawn again.

    The back (shape, posture) is kept but for ``arm_gap`` (arms hanging close to the trunk
    touch it otherwise); the person's head size, occiput and hair colour are kept.

    Parameters
    ----------
    body : BodyParameters
        The person as first seen.
    seed : int
        Seed of the draw.

    Returns
    -------
    BodyParameters
    """
    from rasterserver.simulator.body import ARM_POSTURES

    rng = np.random.default_rng([int(seed), 0xD7E55])
    posture = str(rng.choice(ARM_POSTURES))
    back = body.back
    if posture == "close":
        back = dataclasses.replace(back, arm_gap=float(rng.uniform(0.0, 8.0)))
    return dataclasses.replace(
        body,
        back=back,
        arm_posture=posture,
        arm_abduction=float(rng.uniform(12.0, 40.0)),
        head_tilt=float(rng.uniform(-15.0, 20.0)),
        hair_length=float(np.clip(body.hair_length + rng.uniform(-30.0, 30.0), 0.0, 150.0)),
        hair_seed=int(rng.integers(0, 2**31 - 1)),
        waistband=float(rng.uniform(1.05, 1.4)) if rng.random() < 0.75 else None,
        cloth_albedo=float(rng.uniform(0.05, 0.8)),
        cloth_thickness=float(rng.uniform(1.5, 8.0)),
    )


def role_body(seed: int, role: str) -> Any:
    """The parameters of acquisition ``role`` of person ``seed``."""
    from rasterserver.simulator.back import posture_sway
    from rasterserver.simulator.body import random_body

    cmp = _bench("comparison")
    base = random_body(seed)

    def visit(k: int, **grow: float) -> Any:
        other = redress(base, 7919 * seed + k)
        back = cmp.grown(other.back, **grow) if grow else other.back
        return dataclasses.replace(other, back=posture_sway(back, 7919 * seed + k))

    return {
        "A": lambda: base,
        "B": lambda: dataclasses.replace(base, back=cmp.repose(base.back, seed)),
        "C": lambda: dataclasses.replace(base, back=cmp.grown(base.back, rotation=3.0)),
        "D": lambda: base,
        "E": lambda: visit(1),
        "F": lambda: visit(2, deviation=5.0),
        "G": lambda: visit(3, rotation=3.0),
        "H": lambda: visit(4),
        "I": lambda: visit(5),
    }[role]()


_STATE: dict[str, Any] = {}


def run_task(task: tuple[int, str, str]) -> dict[str, Any]:
    """Render, reconstruct and analyse one acquisition of one kind; its Visit and truth."""
    from rasterserver.simulator.back import make_back
    from rasterserver.simulator.body import clinic_station, make_body
    from rasterserver.simulator.render import render
    from rasterserver.stage import StageContext

    seed, role, kind = task
    cmp = _bench("comparison")
    code = _bench("real_bodies").CODES[seed % 4]
    station = clinic_station(seed, code)
    context = StageContext(calibration=station, raster=station.raster_definition)
    body = role_body(seed, role)
    scene = make_body(body) if kind == "body" else make_back(body.back)
    settings = _bench("numbering_backs")._settings(seed).replace(threads=1)
    t0 = time.perf_counter()
    image = render(
        scene, station, settings=settings, seed=300_000 + 10 * seed + cmp.ROLES.index(role)
    )
    return {
        "seed": seed,
        "role": role,
        "kind": kind,
        "posture": body.arm_posture,
        "params": body.back.to_dict(),
        **cmp.acquisition(scene, image.image, context, role=role, label=f"{seed}:{role}:{kind}"),
        "seconds": time.perf_counter() - t0,
    }


def _safe(task: tuple[int, str, str]) -> dict[str, Any]:
    try:
        return run_task(task)
    except Exception as exc:  # a crash is a result too: count it, keep going
        return {"seed": task[0], "role": task[1], "kind": task[2], "error": f"{exc!r}"}


def _why(reason: str) -> str:
    """A refusal's reason without the visit's label and the figures, to tally."""
    text = re.sub(r"^visit \S+ ", "", reason).split(";")[0]
    return re.sub(r"[-+]?\d+(\.\d+)?", "#", text).strip()[:100]


def thresholds(version: str) -> Any:
    """The comparison's thresholds of ``version`` ("" the defaults, "_v1" version 1,
    "_v3" version 3 with asymmetry version 2, "_a3" the defaults with asymmetry version 3)."""
    from rasterserver.comparison import THRESHOLDS

    if version == "_v1":
        return dataclasses.replace(
            THRESHOLDS, displaced_limit=None, axis_window=None, partial_frame=False
        )
    if version == "_v3":
        return dataclasses.replace(THRESHOLDS, through_slack=None, mirror_reach=None)
    if version == "_a3":
        return dataclasses.replace(THRESHOLDS, mirror_reach=None)
    return THRESHOLDS


def score_person(rows: dict[str, dict[str, Any]], version: str = "") -> dict[str, Any]:
    """``comparison.score_back`` of one person's nine acquisitions of one kind, plus what a
    clinician would not get: refused registrations and progressions without an answer."""
    cmp = _bench("comparison")
    s = cmp.score_back(rows, thresholds(version))
    refused = {}
    if "refused" in s["registration"]:
        refused["B"] = _why(s["registration"]["refused"])
    for y, entry in s["maps"].items():
        if "refused" in entry:
            refused[y] = _why(entry["refused"])
    s["refused"] = refused
    s["no_frame"] = sorted(r for r in rows if not rows[r]["frame"])
    # the true change of each progression pair, in the order of its flags: a grown curve
    # need not change the back's largest deviation or rotation (another curve holds it)
    tr = {r: rows[r]["truth"] for r in rows}
    s["deviation_true"] = [
        tr["F"]["lateral_deviation_max_mm"] - tr[x]["lateral_deviation_max_mm"]
        for x in cmp.UNCHANGED
    ]
    s["rotation_true"] = [
        tr[y]["surface_rotation_max_deg"] - tr[x]["surface_rotation_max_deg"]
        for y in ("C", "G")
        for x in cmp.UNCHANGED
    ]
    s["posture"] = {r: rows[r]["posture"] for r in rows}
    return s


def stamp() -> str:
    """The analysis and comparison code a row was computed with."""
    import rasterserver

    digest = hashlib.sha256()
    root = Path(rasterserver.__file__).parent
    for path in sorted([*root.glob("comparison/*.py"), root / "pair_comparison.py"]):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return _bench("analysis").analysis_code() + f" comparison {digest.hexdigest()[:12]}"


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per kind: ``comparison.summarise`` and the refusals."""
    from rasterserver.trends import sdc

    cmp = _bench("comparison")
    out: dict[str, Any] = {
        "people": len(rows),
        "crashed": [r["seed"] for r in rows if "error" in r],
    }
    good = [r for r in rows if "error" not in r]
    for kind in [k + v for v in VERSIONS for k in KINDS]:
        scores = [r[kind] for r in good if kind in r]
        if not scores:
            continue
        entry = cmp.summarise(scores)
        why: Counter[str] = Counter()
        for s in scores:
            for y, reason in s["refused"].items():
                why[f"{y}: {reason}"] += 1
        entry["refused_pairs"] = {y: sum(y in s["refused"] for s in scores) for y in PAIRS}
        entry["refusals"] = dict(why.most_common(10))
        entry["no_frame"] = sum(len(s["no_frame"]) for s in scores)
        for name, third in (("carried", False), ("carried_third", True)):
            moved = [c for s in scores for c in s.get("carried", []) if ("third" in c) == third]
            errors = [c["vp_error_mm"] for c in moved if "vp_error_mm" in c]
            entry[name] = {
                "pairs": len(moved),
                "carried": sum("refused" not in c for c in moved),
                "refused": dict(Counter(c["refused"] for c in moved if "refused" in c)),
                "vp_error_mm": {
                    "median": float(np.median(errors)) if errors else math.nan,
                    "max": float(np.max(errors)) if errors else math.nan,
                },
            }
        entry["acquisitions"] = 9 * len(scores)
        for name, key in (
            ("deviation", "lateral_deviation_max_mm"),
            ("rotation", "surface_rotation_max_deg"),
        ):
            sets = [f for s in scores for f in s[f"{name}_flags"]]
            entry["trends"][f"{name}_unanswered"] = sum(f.get(key) is None for f in sets)
            entry["trends"][f"{name}_pairs"] = len(sets)
            # flagged among the answered pairs whose true change is at least twice the
            # smallest detectable change (where detection is promised, ≥ 97 %)
            limit = 2.0 * (sdc(key) or math.inf)
            due = [
                f.get(key)
                for s in scores
                for f, true in zip(s[f"{name}_flags"], s.get(f"{name}_true", []), strict=False)
                if abs(true) >= limit and f.get(key) is not None
            ]
            entry["trends"][f"{name}_due"] = {
                "n": len(due),
                "flagged": sum(bool(v) for v in due),
                "fraction": sum(bool(v) for v in due) / len(due) if due else math.nan,
                "two_sdc": limit,
            }
        out[kind] = entry
    return out


def _f(v: Any, nd: int = 2) -> str:
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{nd}f}"


def markdown(s: dict[str, Any]) -> str:
    """The summary as a markdown table, body against back alone."""
    kinds = [k + v for v in VERSIONS for k in KINDS if k + v in s]

    def med_max(path: tuple[str, ...], nd: int = 2) -> list[str]:
        cells = []
        for k in kinds:
            d = s[k]
            for p in path:
                d = d[p]
            cells.append(f"{_f(d['median'], nd)} / {_f(d['max'], nd)}")
        return cells

    def pct(name: str) -> list[str]:
        cells = []
        for k in kinds:
            d = s[k]["trends"][name]
            cells.append(
                f"{100 * d['fraction']:.1f} % ({d['flagged']}/{d['n']})" if d["n"] else "–"
            )
        return cells

    rows: list[tuple[str, list[str]]] = [
        (
            "acquisitions without a body frame (VP, DL or DR refused)",
            [f"{s[k]['no_frame']}/{s[k]['acquisitions']}" for k in kinds],
        ),
        *[
            (f"A→{y} refused", [f"{s[k]['refused_pairs'][y]}/{s['people']}" for k in kinds])
            for y in PAIRS
        ],
        (
            "B onto A: error at the trunk centre (mm), median / max",
            med_max(("registration", "error_mm")),
        ),
        ("B onto A: rotation error (°)", med_max(("registration", "error_deg"))),
        ("A→C: map − true change, rms (mm)", med_max(("maps", "C", "error_rms_mm"))),
        ("A→D (no change, same dress): map rms (mm)", med_max(("maps", "D", "rms_mm"))),
        ("A→E (no change, another visit's dress): map rms (mm)", med_max(("maps", "E", "rms_mm"))),
        (
            "A→D: asymmetry change rms (mm; truth 0)",
            med_max(("maps", "D", "asymmetry_change_rms_mm")),
        ),
        (
            "A→E: asymmetry change rms (mm; truth 0)",
            med_max(("maps", "E", "asymmetry_change_rms_mm")),
        ),
        (
            "A→E: asymmetry change p99 of its \\|values\\| (mm)",
            med_max(("maps", "E", "asymmetry_change_p99_mm")),
        ),
        ("noise-only pairs: parameter changes flagged", pct("noise")),
        ("deviation +5 mm: `lateral_deviation_max_mm` flagged", pct("deviation_max")),
        ("  of those whose true change is ≥ 2 SDC", pct("deviation_due")),
        (
            "  progressions without an answer (parameter refused)",
            [
                f"{s[k]['trends']['deviation_unanswered']}/{s[k]['trends']['deviation_pairs']}"
                for k in kinds
            ],
        ),
        ("rotation +3°: `surface_rotation_max_deg` flagged", pct("rotation_max")),
        ("  of those whose true change is ≥ 2 SDC", pct("rotation_due")),
        (
            "  progressions without an answer (parameter refused)",
            [
                f"{s[k]['trends']['rotation_unanswered']}/{s[k]['trends']['rotation_pairs']}"
                for k in kinds
            ],
        ),
        (
            "pairs with VP at one visit only: VP carried / pairs (refused: reach, registration)",
            [
                f"{s[k]['carried']['carried']}/{s[k]['carried']['pairs']} "
                f"({s[k]['carried']['refused'].get('reach', 0)}, "
                f"{s[k]['carried']['refused'].get('registration', 0)})"
                for k in kinds
            ],
        ),
        (
            "  carried VP's distance from the true VP (mm), median / max",
            med_max(("carried", "vp_error_mm")),
        ),
        (
            "pairs with VP at neither visit: VP carried to both from a third / pairs",
            [f"{s[k]['carried_third']['carried']}/{s[k]['carried_third']['pairs']}" for k in kinds],
        ),
        (
            "  carried VP's distance from the true VP (mm), median / max (worse of the two)",
            med_max(("carried_third", "vp_error_mm")),
        ),
        ("one comparison (s), median / max", med_max(("pair_s",))),
    ]
    lines = ["| figure | " + " | ".join(kinds) + " |", "|---" + "|---:" * len(kinds) + "|"]
    lines += [f"| {label} | " + " | ".join(cells) + " |" for label, cells in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument(
        "--first-seed", type=int, default=0, help="first seed (tuning 0; fresh held out from 43300)"
    )
    ap.add_argument("--people", type=int, default=20, help="people with a curved back")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/clinic-comparison.jsonl"))
    ap.add_argument("--summary", type=Path, default=None, help="only summarise this file")
    args = ap.parse_args(argv)
    if args.summary is not None:
        s = summary(read_rows(args.summary))
        print(json.dumps(s, indent=2, default=float))
        print(markdown(s))
        return 0
    if args.people < 1:
        ap.error("--people must be at least 1")
    code = stamp()
    rows = read_rows(args.out)
    if any(r.get("stamp") != code for r in rows):
        ap.error(f"{args.out} holds rows of other analysis or comparison code; give another --out")
    done = {r["seed"] for r in rows}
    seeds = [s for s in people(args.first_seed, args.people) if s not in done]
    cmp = _bench("comparison")
    todo = [(s, role, kind) for s in seeds for kind in KINDS for role in cmp.ROLES]
    print(f"{len(done)} people done, {len(seeds)} to go ({len(todo)} acquisitions)", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    pending: dict[int, dict[str, dict[str, dict[str, Any]]]] = {}
    start = time.time()
    with (
        mp.get_context("spawn").Pool(args.workers, maxtasksperchild=40) as pool,
        args.out.open("a") as fh,
    ):
        for i, res in enumerate(pool.imap(_safe, todo, chunksize=1), 1):
            person = pending.setdefault(res["seed"], {k: {} for k in KINDS})
            person[res["kind"]][res["role"]] = res
            if all(len(person[k]) == len(cmp.ROLES) for k in KINDS):
                del pending[res["seed"]]
                errors = [r["error"] for k in KINDS for r in person[k].values() if "error" in r]
                row: dict[str, Any] = {"seed": res["seed"], "stamp": code}
                if errors:
                    row["error"] = errors[0]
                else:
                    try:
                        for k in KINDS:
                            for v in VERSIONS:
                                row[k + v] = score_person(person[k], v)
                    except Exception as exc:  # a crash in the comparison is a result too
                        row = {"seed": res["seed"], "stamp": code, "error": f"{exc!r}"}
                fh.write(json.dumps(row, default=float) + "\n")
                fh.flush()
                rate = (time.time() - start) / i
                print(
                    f"{i}/{len(todo)} person {res['seed']} {row.get('error', 'ok')} "
                    f"{rate:.2f} s each",
                    flush=True,
                )
    s = summary(read_rows(args.out))
    print(json.dumps(s, indent=2, default=float))
    print(markdown(s))
    return 0


if __name__ == "__main__":
    sys.exit(main())
