"""The archive's size and contents: ``rasterserver stats``.

* **files by kind**: raw frames (``raw/``), derived results per stage kind (``derived/``,
  the stage read from the file name), partial writes, the SQLite catalogue (when it lives in
  the archive), exports and anything else; bytes and file counts each;
* **catalogue**: acquisitions, frames, stored results, pipeline runs, processing jobs;
* **results per chain**: every distinct chain that ends in a stored result without children
  (the plugins, versions and parameters hashes from its first stage to its last), with how
  many acquisitions have it;
* **what prune would free** (:func:`rasterserver.prune.plan_prune` with its defaults), when
  asked.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sqlalchemy import func, select

from rasterserver.archive import Archive
from rasterserver.catalog.job_models import ProcessingJob
from rasterserver.catalog.models import Acquisition, Frame, PipelineRun, StageResult
from rasterserver.chain_spec import ResultRow, result_rows

__all__ = ["ArchiveStats", "archive_stats", "file_kinds"]

_DERIVED = re.compile(r"[0-9a-f]{32}\.(?P<stage>[a-z][a-z0-9_-]{0,31})-[0-9a-f]{32}\.h5$")
_PAGE = 500


@dataclass
class ArchiveStats:
    """See the module docstring. Sizes in bytes."""

    files: dict[str, dict[str, int]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    chains: list[dict[str, Any]] = field(default_factory=list)
    prune: dict[str, Any] | None = None

    @property
    def total_bytes(self) -> int:
        """Bytes of every file in the archive folder."""
        return sum(kind["bytes"] for kind in self.files.values())

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {"total_bytes": self.total_bytes, "files": self.files, "counts": self.counts,
                "chains": self.chains, "prune": self.prune}


def _kind(relative: str) -> str:
    parts = relative.split("/")
    if parts[0] == "raw":
        return "raw frames"
    if parts[0] == "derived":
        if ".tmp-" in parts[-1]:
            return "partial writes"
        match = _DERIVED.match(parts[-1])
        return f"derived {match['stage']}" if match else "derived (other)"
    if parts[0].startswith("catalog"):
        return "catalogue"
    if parts[0] == "exports":
        return "exports"
    return "other"


def file_kinds(root: Path) -> dict[str, dict[str, int]]:
    """Bytes and file count per kind of file under the archive folder ``root``."""
    out: dict[str, dict[str, int]] = {}
    for folder, _dirs, names in os.walk(root):
        for name in names:
            path = Path(folder) / name
            try:
                size = path.stat().st_size
            except OSError:
                continue  # removed while walking
            kind = _kind(path.relative_to(root).as_posix())
            entry = out.setdefault(kind, {"bytes": 0, "files": 0})
            entry["bytes"] += size
            entry["files"] += 1
    return dict(sorted(out.items()))


def _chains(archive: Archive) -> list[dict[str, Any]]:
    """Distinct chains ending in a result without children, with their acquisitions."""
    with archive.session() as s:
        ids = list(s.scalars(select(func.distinct(StageResult.acquisition_id))))
    seen: dict[tuple[str, ...], set[int]] = {}
    for start in range(0, len(ids), _PAGE):
        with archive.session() as s:
            pages = result_rows(s, ids[start : start + _PAGE])
        for acquisition_id, rows in pages.items():
            by_id = {row.id: row for row in rows}
            parents = {row.parent_id for row in rows}
            for row in rows:
                if row.id in parents:
                    continue
                steps: list[str] = []
                at: ResultRow | None = row
                while at is not None:
                    steps.insert(0, f"{at.plugin}@{at.plugin_version}#{at.params_hash[:8]}")
                    at = by_id.get(at.parent_id) if at.parent_id is not None else None
                seen.setdefault(tuple(steps), set()).add(acquisition_id)
    return sorted(
        ({"chain": " > ".join(k), "last_stage": k[-1].split(".")[0],
          "acquisitions": len(v)} for k, v in seen.items()),
        key=lambda c: (-c["acquisitions"], c["chain"]),
    )


def archive_stats(
    archive: Archive, *, prune: bool = False, progress: Callable[[int, int], None] | None = None
) -> ArchiveStats:
    """Measure the archive (see the module docstring); with ``prune``, what prune would free.

    Returns
    -------
    ArchiveStats
    """
    stats = ArchiveStats(files=file_kinds(archive.settings.archive))
    with archive.session() as s:
        for name, model in (("acquisitions", Acquisition), ("frames", Frame),
                            ("results", StageResult), ("pipeline runs", PipelineRun),
                            ("processing jobs", ProcessingJob)):
            stats.counts[name] = int(s.scalar(select(func.count()).select_from(model)) or 0)
    stats.chains = _chains(archive)
    if prune:
        from rasterserver.prune import plan_prune

        stats.prune = plan_prune(archive, progress=progress).to_dict()
    return stats
