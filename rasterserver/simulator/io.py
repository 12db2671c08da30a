"""Write a simulated acquisition to a folder: image, ground truth, calibration and raster."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rasterserver.optics import Station
from rasterserver.simulator.ground_truth import save_ground_truth
from rasterserver.simulator.render import Rendering
from rasterserver.simulator.scene import Scene


def write_simulation(
    folder: str | Path,
    rendering: Rendering,
    scene: Scene,
    station: Station,
    *,
    stem: str = "frame",
    ground_truth_format: str = "npz",
) -> dict[str, Path]:
    """Write one rendering and everything needed to process and check it.

    Files (the folder is created if needed; existing files are overwritten):

    * ``<stem>.png`` — the frame (8-bit, or 16-bit PNG for deeper images; pixel values as
      digitised, not rescaled);
    * ``<stem>.npy`` — the same frame as a NumPy array;
    * ``<stem>_truth.npz`` (or ``.h5``) — ground truth, see
      :func:`rasterserver.simulator.ground_truth.save_ground_truth`;
    * ``calibration.json`` — the station (``rasterserver.calibration/1``), with the raster
      as the station holds it (inline or by name);
    * ``raster.json`` — the raster definition (``rasterserver.raster/1``).

    Parameters
    ----------
    folder : str or Path
        Output folder.
    rendering : Rendering
        From :func:`rasterserver.simulator.render.render`.
    scene : Scene
        The rendered scene (landmarks and metadata go into the ground truth).
    station : Station
        The station it was rendered with.
    stem : str
        Base name of the per-frame files.
    ground_truth_format : str
        ``"npz"`` or ``"h5"``.

    Returns
    -------
    dict of str to Path
        Keys ``"image_png"``, ``"image_npy"``, ``"ground_truth"``, ``"calibration"``,
        ``"raster"``.
    """
    if ground_truth_format not in ("npz", "h5"):
        raise ValueError("ground_truth_format must be 'npz' or 'h5'")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {
        "image_png": folder / f"{stem}.png",
        "image_npy": folder / f"{stem}.npy",
        "ground_truth": folder / f"{stem}_truth.{ground_truth_format}",
        "calibration": folder / "calibration.json",
        "raster": folder / "raster.json",
    }
    image = np.ascontiguousarray(rendering.image)
    if not cv2.imwrite(str(paths["image_png"]), image):
        raise OSError(f"could not write {paths['image_png']}")
    np.save(paths["image_npy"], image)
    save_ground_truth(paths["ground_truth"], rendering, scene, station)
    station.save(paths["calibration"])
    station.raster_definition.save(paths["raster"])
    return paths
