"""Scenes scored in worker processes, with progress on stderr, and the command line they
share (the scene-by-scene benchmarks that keep no rows on disk: ``numbering_ablation.py``,
``back_losses.py``, ``flanked_peaks.py``)."""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = ["add_scene_arguments", "report", "scene_rows", "scene_seeds"]


def add_scene_arguments(ap: argparse.ArgumentParser) -> None:
    """The range, raster, frame cache, workers and ``--out`` every such script takes."""
    ap.add_argument("--first-seed", type=int, default=7600)
    ap.add_argument("--scenes", type=int, default=100)
    ap.add_argument("--raster", default=None, help="see every scene through this raster")
    ap.add_argument("--cache", type=Path, default=None, help="folder of rendered frames")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="write the summary here (JSON)")


def scene_seeds(
    ap: argparse.ArgumentParser, args: argparse.Namespace, rasters: Sequence[str]
) -> list[int]:
    """The seeds of ``args``' range, after refusing an unknown raster (one of ``rasters``)
    or an empty range through ``ap`` (exit 2); the frame cache folder made."""
    if args.raster is not None and args.raster not in rasters:
        ap.error(f"unknown raster {args.raster!r}; built in: {', '.join(rasters)}")
    if args.scenes < 1:
        ap.error("--scenes must be at least 1")
    if args.cache is not None:
        args.cache.mkdir(parents=True, exist_ok=True)
    return list(range(args.first_seed, args.first_seed + args.scenes))


def report(summary: dict[str, Any], args: argparse.Namespace, table: str | None = None) -> int:
    """Print ``table`` (the summary as JSON without one), write ``summary`` with its range to
    ``args.out``; the exit code: 1 when a scene failed."""
    summary["range"] = {"first_seed": args.first_seed, "scenes": args.scenes, "raster": args.raster}
    print(table if table is not None else json.dumps(summary, indent=2))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary, indent=2) + "\n")
    return 0 if not summary["error_seeds"] else 1


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
