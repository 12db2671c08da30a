"""One clinic scene of :mod:`real_bodies` looked at closely: its wrong peaks and what a change
of parameters numbers or loses there, listed and drawn.

A scene's totals (``real_bodies.py``) say that a change of a stage's parameters numbers
a peak wrongly or costs the back's coverage; this script says where and how. For one frame
(rendered from its seed, or read from a ``--cache`` folder of ``real_bodies.py``), stages
1-4 run with ``--against`` (default: the installed defaults) and with ``--params``:

* every line holding a wrongly numbered peak under ``--params``: its columns, number,
  the true numbers and objects of its wrong peaks;
* the back's exact line crossings covered (a peak with the correct number) under one
  parameter set and not the other;
* ``--png``: the frame around the wrong peaks (or ``--box``), numbered peaks coloured by
  number, unnumbered ones as crosses, wrong ones red, lines labelled ``line:number`` at
  their first peak, the objects' outlines, and the crossings only ``--against`` covers
  (red rings) or only ``--params`` covers (green rings).

Usage::

    python benchmarks/scene_look.py --seed 7790 --params '{"peaks": {"min_slope": 1.5}}' \\
        --png /tmp/7790.png
    python benchmarks/scene_look.py --seed 7585 --raster mseq8b-35to65 --cache /tmp/twin \\
        --params '{"numbers": {"tile_check": false}}' --box 200,360,660,730 --png /tmp/b.png
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import real_bodies  # beside this script (the path above)


@dataclass
class Look:
    """Stages 1-4 on one frame with one parameter set, scored against the frame's truth."""

    result: Any  # NumberedLines
    truth: np.ndarray  # per peak: true number, -1 none
    obj: np.ndarray  # per peak: object index at its pixel
    covered: np.ndarray  # per exact crossing: carries a peak with its correct number

    @property
    def wrong(self) -> np.ndarray:
        """Per peak: numbered, with a true number, and not that one."""
        return real_bodies.wrong_peaks(self.result.number, self.truth)


def look(frame: real_bodies.Frame, params: dict[str, dict[str, Any]]) -> Look:
    """Run stages 1-4 on ``frame`` with ``params`` and score every peak and crossing."""
    result, _ = real_bodies.run_stages(frame, params)
    truth, obj = real_bodies.peak_truth(frame, result)
    return Look(result, truth, obj, real_bodies.covered_crossings(frame, result, truth))


def wrong_lines(frame: real_bodies.Frame, seen: Look) -> list[dict[str, Any]]:
    """One entry per line holding a wrongly numbered peak."""
    res, wrong = seen.result, seen.wrong
    out = []
    for line in np.unique(res.line_id[wrong]):
        on = res.line_id == line
        bad = on & wrong
        out.append(
            {
                "line": int(line),
                "peaks": int(on.sum()),
                "columns": [int(res.col[on].min()), int(res.col[on].max())],
                "number": int(res.line_number[line]),
                "wrong_peaks": int(bad.sum()),
                "wrong_columns": sorted({int(c) for c in res.col[bad]})[:20],
                "true_numbers": sorted({int(t) for t in seen.truth[bad]}),
                "objects": sorted({frame.names[int(o)] for o in seen.obj[bad] if o >= 0}),
            }
        )
    return out


def _box(
    frame: real_bodies.Frame, seen: Look, box: tuple[int, ...] | None, pad: int
) -> tuple[int, ...]:
    """``c0, c1, r0, r1``: ``box``, else around the wrong peaks, else the frame."""
    h, w = frame.image.shape
    if box:
        c0, c1, r0, r1 = box
    elif np.any(seen.wrong):
        res, wrong = seen.result, seen.wrong
        c0, c1 = int(res.col[wrong].min()) - pad, int(res.col[wrong].max()) + pad
        r0, r1 = int(res.row[wrong].min()) - pad, int(res.row[wrong].max()) + pad
    else:
        c0, c1, r0, r1 = 0, w, 0, h
    return max(c0, 0), min(c1, w), max(r0, 0), min(r1, h)


def draw(
    frame: real_bodies.Frame, seen: Look, before: Look, box: tuple[int, ...], path: Path
) -> None:
    """Write the picture described in the module's docstring to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c0, c1, r0, r1 = box
    res, wrong = seen.result, seen.wrong
    width = 12.0
    fig, ax = plt.subplots(figsize=(width, max(2.0, width * (r1 - r0) / max(c1 - c0, 1))))
    ax.imshow(
        frame.image[r0:r1, c0:c1], cmap="gray", extent=(c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5)
    )
    inside = (res.col >= c0) & (res.col < c1) & (res.row >= r0) & (res.row < r1)
    small = 3 if (c1 - c0) > 200 else 8
    ok = inside & (res.number >= 0) & ~wrong
    ax.scatter(
        res.col[ok], res.row[ok], s=small, c=res.number[ok] % 10, cmap="tab10", vmin=0, vmax=9
    )
    off = inside & (res.number < 0)
    ax.scatter(res.col[off], res.row[off], s=small, c="0.6", marker="x")
    ax.scatter(res.col[inside & wrong], res.row[inside & wrong], s=4 * small, c="red")
    if (c1 - c0) <= 200:
        for line in np.unique(res.line_id[inside & (res.line_id >= 0)]):
            first = np.flatnonzero((res.line_id == line) & inside)[0]
            label = f"{line}:{res.line_number[line]}"
            ax.text(res.col[first], res.row[first], label, fontsize=6, color="yellow")
    lr = frame.line_rows
    on = frame.lr_on_back & (lr.column >= c0) & (lr.column < c1) & (lr.row >= r0) & (lr.row < r1)
    for only, colour in (
        (before.covered & ~seen.covered, "red"),
        (seen.covered & ~before.covered, "lime"),
    ):
        sel = on & only
        ax.scatter(lr.column[sel], lr.row[sel], s=6 * small, facecolors="none", edgecolors=colour)
    objects = frame.object_index[r0:r1, c0:c1]
    if objects.size and objects.max() > objects.min():
        levels = np.arange(objects.min() - 0.5, objects.max() + 1)
        ax.contour(
            np.arange(c0, c1),
            np.arange(r0, r1),
            objects,
            levels=levels,
            colors="cyan",
            linewidths=0.5,
        )
    ax.set_title(f"scene {frame.seed} ({frame.code}): {int(wrong.sum())} wrong peaks")
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def _params(text: str, flag: str, ap: argparse.ArgumentParser) -> dict[str, dict[str, Any]]:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        ap.error(f"{flag} is not JSON: {exc}")
    if not isinstance(value, dict) or not all(isinstance(v, dict) for v in value.values()):
        ap.error(f'{flag} must map stages to parameters, e.g. {{"peaks": {{"min_slope": 1.5}}}}')
    return value


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--seed", type=int, required=True, help="the scene (real_bodies.py's seed)")
    ap.add_argument(
        "--raster",
        choices=sorted(real_bodies._raster_names()),
        default=None,
        help="see the scene through this built-in raster instead of the seed's code",
    )
    ap.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="real_bodies.py's frame folder: read when the scene is there, kept there when not",
    )
    ap.add_argument("--params", default="{}", help="stage parameters looked at (JSON)")
    ap.add_argument("--against", default="{}", help="stage parameters compared with (JSON)")
    ap.add_argument("--png", type=Path, default=None, help="write the picture here")
    ap.add_argument("--box", default=None, help="picture's columns and rows: c0,c1,r0,r1")
    ap.add_argument("--pad", type=int, default=20, help="pixels around the wrong peaks")
    args = ap.parse_args(argv)
    params = _params(args.params, "--params", ap)
    against = _params(args.against, "--against", ap)
    box = None
    if args.box is not None:
        parts = args.box.split(",")
        if len(parts) != 4 or not all(p.strip().lstrip("-").isdigit() for p in parts):
            ap.error("--box takes four integers: c0,c1,r0,r1")
        box = tuple(int(p) for p in parts)
    if args.cache is not None:
        args.cache.mkdir(parents=True, exist_ok=True)
    frame = real_bodies.cached_frame(args.seed, args.raster, args.cache)
    seen, before = look(frame, params), look(frame, against)
    back = frame.lr_on_back
    report = {
        "seed": frame.seed,
        "code": frame.code,
        "wrong_peaks": int(seen.wrong.sum()),
        "wrong_peaks_against": int(before.wrong.sum()),
        "back_crossings": int(back.sum()),
        "back_covered": int((seen.covered & back).sum()),
        "back_covered_against": int((before.covered & back).sum()),
        "back_only_against": int((before.covered & ~seen.covered & back).sum()),
        "back_only_params": int((seen.covered & ~before.covered & back).sum()),
        "wrong_lines": wrong_lines(frame, seen),
        "reason": seen.result.reason,
    }
    print(json.dumps(report, indent=2))
    if args.png is not None:
        draw(frame, seen, before, _box(frame, seen, box, args.pad), args.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
