"""Scenes scored in worker processes, with progress on stderr (the pool of the scene-by-scene
benchmarks that keep no rows on disk: ``numbering_ablation.py``, ``back_losses.py``)."""

from __future__ import annotations

import multiprocessing as mp
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["scene_rows"]


def scene_rows(
    work: Callable[[int], dict[str, Any]],
    seeds: Sequence[int],
    *,
    workers: int,
    initializer: Callable[..., None],
    initargs: tuple[Any, ...],
) -> list[dict[str, Any]]:
    """``work(seed)`` for every seed in ``workers`` spawned processes, rows as they come.

    Parameters
    ----------
    work : callable
        A module-level function of the seed returning its row; a row with an ``error``
        is reported at once (``work`` catches its own exceptions).
    seeds : sequence of int
        The scenes.
    workers : int
        Processes (at least one).
    initializer, initargs
        Run once in each process (the script's settings: frame cache, raster, ...).

    Returns
    -------
    list of dict
        The rows in the order they finished.
    """
    rows: list[dict[str, Any]] = []
    start = time.time()
    with mp.get_context("spawn").Pool(
        max(1, workers), initializer=initializer, initargs=initargs, maxtasksperchild=40
    ) as pool:
        for i, row in enumerate(pool.imap_unordered(work, seeds, chunksize=1), 1):
            rows.append(row)
            if i % 20 == 0 or i == len(seeds) or "error" in row:
                print(
                    f"{i}/{len(seeds)} scenes, {(time.time() - start) / i:.2f} s/scene"
                    + (f"; seed {row['seed']}: {row['error']}" if "error" in row else ""),
                    file=sys.stderr,
                    flush=True,
                )
    return rows
