"""Regenerate the README pictures of a simulated rasterstereograph and its ground truth.

Writes to ``docs/img/``:

* ``simulated_back_moderate.png`` — the camera frame of the ``moderate`` preset back (right
  thoracic scoliosis, 15 mm lateral deviation, 8° rotation) at the seed's station, exactly as
  digitised (8 bit, 576 x 604, noise seed 0);
* ``simulated_back_moderate_depth.png`` — the exact depth (world Z, mm) seen at every pixel,
  colour-mapped with a scale bar, with the true landmarks drawn in: the spinal midline
  (white), the vertebra prominens C7 and the two lumbar dimples (circles);
* ``simulated_back_moderate_pair.png`` — both side by side.

Usage::

    python benchmarks/make_readme_images.py [--preset moderate] [--out docs/img]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from rasterserver.optics import default_station
from rasterserver.simulator.back import make_back, preset
from rasterserver.simulator.render import RenderSettings, render


def depth_picture(
    points: np.ndarray, visible: np.ndarray, *, z_range: tuple[float, float] | None = None
) -> tuple[np.ndarray, tuple[float, float]]:
    """Colour-map the Z of ``points`` (near: red, far: blue); background black."""
    z = points[..., 2]
    if z_range is None:
        lo, hi = np.percentile(z[visible], [0.5, 99.5])
        lo, hi = 10.0 * np.floor(lo / 10.0), 10.0 * np.ceil(hi / 10.0)
    else:
        lo, hi = z_range
    scaled = np.clip((hi - np.nan_to_num(z, nan=hi)) / (hi - lo), 0.0, 1.0)
    colour = cv2.applyColorMap((255 * scaled).astype(np.uint8), cv2.COLORMAP_TURBO)
    colour[~visible] = 0
    return colour, (lo, hi)


def scale_bar(height: int, z_range: tuple[float, float], *, width: int = 90) -> np.ndarray:
    """A vertical colour bar with tick labels in mm matching :func:`depth_picture`."""
    lo, hi = z_range
    bar = np.zeros((height, width, 3), np.uint8)
    top, bottom = 44, height - 30
    ramp = np.linspace(1.0, 0.0, bottom - top)  # near (lo) at the top
    colours = cv2.applyColorMap((255 * ramp).astype(np.uint8)[:, None], cv2.COLORMAP_TURBO)
    bar[top:bottom, 8:28] = colours
    font = cv2.FONT_HERSHEY_SIMPLEX
    step = 20.0 if hi - lo <= 200 else 50.0
    for value in np.arange(np.ceil(lo / step) * step, hi + 1e-6, step):
        row = round(top + (value - lo) / (hi - lo) * (bottom - top - 1))
        cv2.line(bar, (28, row), (34, row), (255, 255, 255), 1)
        cv2.putText(bar, f"{value:+.0f}", (37, row + 4), font, 0.38, (255, 255, 255), 1)
    cv2.putText(bar, "Z mm", (6, 18), font, 0.45, (255, 255, 255), 1)
    cv2.putText(bar, "near", (6, 36), font, 0.38, (255, 255, 255), 1)
    cv2.putText(bar, "far", (6, height - 12), font, 0.38, (255, 255, 255), 1)
    return bar


def draw_landmarks(image: np.ndarray, landmarks: dict, project) -> None:
    """Draw the spinal midline and the C7 / dimple points onto ``image`` in place."""
    midline = project(np.asarray(landmarks["spinal_midline"]))
    pts = np.rint(midline).astype(np.int32).reshape(-1, 1, 2)
    cv2.polylines(image, [pts], False, (255, 255, 255), 1, cv2.LINE_AA)
    for name in ("vertebra_prominens", "dimple_left", "dimple_right"):
        u, v = project(np.asarray(landmarks[name])[None])[0]
        cv2.circle(image, (round(u), round(v)), 5, (255, 255, 255), 1, cv2.LINE_AA)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="moderate")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent.parent / "docs" / "img")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    station = default_station()
    scene = make_back(preset(args.preset))
    rendering = render(scene, station, settings=RenderSettings(), seed=args.seed)
    frame = rendering.image
    stem = f"simulated_back_{args.preset}"
    cv2.imwrite(str(args.out / f"{stem}.png"), frame)

    depth, z_range = depth_picture(rendering.points, rendering.visible)
    draw_landmarks(depth, dict(scene.landmarks), station.camera.project)
    depth = np.concatenate([depth, scale_bar(depth.shape[0], z_range)], axis=1)
    cv2.imwrite(str(args.out / f"{stem}_depth.png"), depth)

    gap = np.zeros((frame.shape[0], 8, 3), np.uint8)
    pair = np.concatenate([cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR), gap, depth], axis=1)
    cv2.imwrite(str(args.out / f"{stem}_pair.png"), pair)
    for name in (f"{stem}.png", f"{stem}_depth.png", f"{stem}_pair.png"):
        print(args.out / name)


if __name__ == "__main__":
    main()
