"""Resuming a scene-by-scene benchmark run only with the stages it was started with.

``real_bodies.py`` and ``numbering_backs.py`` append one JSON row per scene to ``--out`` and,
run again, skip the scenes already there. Rerun with other ``--params`` or after a plugin's
version changed, they used to skip them all the same and summarise the old rows as if they
were the new stages' (a tuning comparison read one version twice). Each row now carries
the stamp of its stages; a file holding rows of another stamp is refused.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["chain_stamp", "done_seeds", "read_rows"]


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The JSON rows of a run's ``--out`` (none when it does not exist yet)."""
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def chain_stamp(params: dict[str, Any] | None) -> dict[str, Any]:
    """The stages a row was computed with: stage parameters and plugin name and version.

    Parameters
    ----------
    params : dict, optional
        ``--params``: per-stage parameters over the plugins' defaults.

    Returns
    -------
    dict
        ``{"params": ..., "plugins": {"peaks": "peaks.first-moment 4", ...}}``.
    """
    from rasterserver_plugins.line_numbering import CodeWindowNumbering
    from rasterserver_plugins.line_search import HierarchicalLineSearch
    from rasterserver_plugins.line_sequence import HierarchicalLineOrder
    from rasterserver_plugins.peak_detection import FirstMomentPeaks

    stages = (FirstMomentPeaks, HierarchicalLineSearch, HierarchicalLineOrder, CodeWindowNumbering)
    return {
        "params": params or {},
        "plugins": {cls.stage: f"{cls.name} {cls.version}" for cls in stages},
    }


def done_seeds(path: Path, stamp: dict[str, Any]) -> set[int]:
    """The seeds already in ``path``, all computed with ``stamp``.

    Parameters
    ----------
    path : Path
        The run's ``--out`` (JSON lines); need not exist.
    stamp : dict
        :func:`chain_stamp` of this run.

    Returns
    -------
    set of int

    Raises
    ------
    SystemExit
        When a row was computed with other stages (or carries no stamp): its rows would be
        summarised with this run's.
    """
    rows = read_rows(path)
    other = [row for row in rows if row.get("stamp") != stamp]
    if other:
        raise SystemExit(
            f"{path} holds {len(other)} row(s) computed with other stages than this run's "
            f"(theirs: {json.dumps(other[0].get('stamp'))}; this run: {json.dumps(stamp)}): "
            "give another --out, or remove the file to start again"
        )
    return {int(row["seed"]) for row in rows}
