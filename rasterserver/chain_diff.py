"""What changed between two chains: their stored results compared, acquisition by acquisition.

For every selected acquisition, the results each chain made are found by provenance
(:mod:`rasterserver.chain_spec`), nothing is recomputed. An acquisition *changed* when any
stage's stored output differs (output checksums: the content hash of the record); only then
are files read, to measure how:

* **displacement**: the two surfaces are height fields on grids whose origins are multiples
  of the spacing, so cells line up; the displacement of a cell is ``z_B - z_A`` (mm, depth
  along the camera axis) over the cells both measured: signed mean (a bias), and the median,
  95th percentile and maximum of its magnitude;
* **coverage**: cells measured by B only (gained) and by A only (lost), in cm²;
* **renumbering**: each numbered peak of A is matched with B's peak in the same pixel column
  within one row; peaks whose line number differs, and the lines (numbers of A) most of whose
  matched peaks got another number;
* **clinical parameters**: each analysis parameter's shift ``B - A`` in its unit.

The report gives per acquisition these figures, over the selection their distributions, and
the worst cases by uid (largest 95th-percentile displacement, most renumbered lines, most
coverage lost, largest parameter shifts). :mod:`rasterserver.chain_diff_report` writes it as
JSON and PNG plots.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from rasterserver.archive import Archive
from rasterserver.chain_spec import ChainSpec, ResultRow, StepPattern, match_path, result_rows
from rasterserver.records import Record
from rasterserver.records_analysis import BackShape
from rasterserver.records_lines import NumberedLines
from rasterserver.records_surface import Surface
from rasterserver.registry import Registry, get_registry

__all__ = ["AcquisitionDiff", "ChainDiff", "diff_chains", "diff_records"]

#: Stage kinds compared when none are given: the ones ``process`` makes by default.
DEFAULT_TARGETS: tuple[str, ...] = ("mesh", "analysis")
#: Worst cases listed per measure.
WORST = 10


@dataclass
class AcquisitionDiff:
    """How one acquisition's results differ between chain A and chain B.

    Attributes
    ----------
    uid : str
        The acquisition.
    status : str
        ``changed``, ``unchanged``, ``missing-a`` or ``missing-b`` (that chain has no stored
        result of a target: process it first).
    changed_stages : list of str
        Stage kinds whose output differs, in chain order.
    displacement : dict or None
        ``mean``, ``median_abs``, ``p95_abs``, ``max_abs`` (mm) and ``cells`` compared.
    coverage : dict or None
        ``a_cm2``, ``b_cm2``, ``gained_cm2``, ``lost_cm2``.
    numbering : dict or None
        ``peaks_matched``, ``peaks_renumbered``, ``peaks_newly_numbered``,
        ``peaks_unnumbered``, ``lines_renumbered``, ``shifts`` (renumbered line count per
        number shift B - A).
    parameters : dict
        Per clinical parameter: ``a``, ``b``, ``shift`` and ``unit``.
    """

    uid: str
    status: str
    changed_stages: list[str] = field(default_factory=list)
    displacement: dict[str, float] | None = None
    coverage: dict[str, float] | None = None
    numbering: dict[str, Any] | None = None
    parameters: dict[str, dict[str, Any]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return asdict(self)


@dataclass
class ChainDiff:
    """The comparison of two chains over a selection (see the module docstring)."""

    chain_a: str
    chain_b: str
    targets: list[str]
    steps_a: dict[str, list[str]]
    steps_b: dict[str, list[str]]
    acquisitions: list[AcquisitionDiff]

    def by_status(self, status: str) -> list[str]:
        """Uids of acquisitions with this status, in selection order."""
        return [a.uid for a in self.acquisitions if a.status == status]

    def summary(self) -> dict[str, Any]:
        """Counts, distributions over the changed acquisitions and the worst cases."""
        changed = [a for a in self.acquisitions if a.status == "changed"]
        counts = {s: len(self.by_status(s))
                  for s in ("changed", "unchanged", "missing-a", "missing-b")}
        p95 = [a.displacement["p95_abs"] for a in changed if a.displacement]
        means = [a.displacement["mean"] for a in changed if a.displacement]
        lines = [a.numbering["lines_renumbered"] for a in changed if a.numbering]
        gained = [a.coverage["gained_cm2"] for a in changed if a.coverage]
        lost = [a.coverage["lost_cm2"] for a in changed if a.coverage]
        shifts: dict[str, list[float]] = {}
        for a in changed:
            for name, p in a.parameters.items():
                if p["shift"] is not None:
                    shifts.setdefault(name, []).append(p["shift"])
        first: dict[str, int] = {}
        for a in changed:
            if a.changed_stages:
                first[a.changed_stages[0]] = first.get(a.changed_stages[0], 0) + 1
        return {
            "acquisitions": len(self.acquisitions),
            **counts,
            "first_changed_stage": first,
            "displacement_p95_mm": _distribution(p95),
            "displacement_mean_mm": _distribution(means),
            "lines_renumbered": _distribution(lines),
            "acquisitions_renumbered": sum(1 for n in lines if n),
            "coverage_gained_cm2": _distribution(gained),
            "coverage_lost_cm2": _distribution(lost),
            "parameter_shifts": {name: _distribution(v) for name, v in sorted(shifts.items())},
            "worst": self.worst(),
        }

    def worst(self, count: int = WORST) -> dict[str, list[dict[str, Any]]]:
        """The acquisitions that changed most, per measure, largest first, with uids."""
        changed = [a for a in self.acquisitions if a.status == "changed"]

        def top(value: Callable[[AcquisitionDiff], float | None]) -> list[dict[str, Any]]:
            scored = [(v, a.uid) for a in changed if (v := value(a)) is not None and v > 0]
            scored.sort(key=lambda t: (-t[0], t[1]))
            return [{"uid": uid, "value": round(v, 4)} for v, uid in scored[:count]]

        def p95(a: AcquisitionDiff) -> float | None:
            return a.displacement["p95_abs"] if a.displacement else None

        def renumbered(a: AcquisitionDiff) -> float | None:
            return float(a.numbering["lines_renumbered"]) if a.numbering else None

        def lost(a: AcquisitionDiff) -> float | None:
            return a.coverage["lost_cm2"] if a.coverage else None

        def shift(name: str) -> Callable[[AcquisitionDiff], float | None]:
            def value(a: AcquisitionDiff) -> float | None:
                found = a.parameters.get(name)
                return abs(found["shift"]) if found and found["shift"] is not None else None

            return value

        out = {"displacement_p95_mm": top(p95), "lines_renumbered": top(renumbered),
               "coverage_lost_cm2": top(lost)}
        for name in sorted({n for a in changed for n in a.parameters}):
            out[f"parameter {name}"] = top(shift(name))
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the chains, summary and every acquisition."""
        return {
            "chain_a": self.chain_a,
            "chain_b": self.chain_b,
            "targets": self.targets,
            "steps_a": self.steps_a,
            "steps_b": self.steps_b,
            "summary": self.summary(),
            "acquisitions": [a.to_dict() for a in self.acquisitions],
        }

    def to_json(self) -> str:
        """:meth:`to_dict` as indented JSON (NaN written as null)."""
        return json.dumps(_finite(self.to_dict()), indent=2)


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def _distribution(values: Sequence[float]) -> dict[str, float | int | None]:
    if not values:
        return {"n": 0, "min": None, "median": None, "p95": None, "max": None}
    array = np.asarray(values, dtype=float)
    return {"n": int(array.size), "min": float(array.min()), "median": float(np.median(array)),
            "p95": float(np.percentile(array, 95)), "max": float(array.max())}


# --- measures of two records -------------------------------------------------------------------


def surface_displacement(
    a: Surface, b: Surface
) -> tuple[dict[str, float] | None, dict[str, float]]:
    """Displacement ``z_B - z_A`` over the cells both surfaces measured, and the coverage.

    Returns
    -------
    displacement : dict or None
        ``mean``, ``median_abs``, ``p95_abs``, ``max_abs`` (mm), ``cells``; None when the
        surfaces share no measured cell or differ in spacing.
    coverage : dict
        ``a_cm2``, ``b_cm2``, ``gained_cm2``, ``lost_cm2``.
    """
    za, zb = np.asarray(a.z, dtype=np.float64), np.asarray(b.z, dtype=np.float64)
    s = float(a.spacing)
    cell_cm2 = (s / 10.0) ** 2
    va, vb = np.isfinite(za), np.isfinite(zb)
    coverage = {"a_cm2": float(va.sum() * cell_cm2), "b_cm2": float(vb.sum() * cell_cm2)}
    if not np.isclose(s, float(b.spacing)):
        coverage |= {"gained_cm2": float("nan"), "lost_cm2": float("nan")}
        return None, coverage
    # grid origins are multiples of the spacing: B's cell (i, j) is A's (i + di, j + dj)
    di = round((float(b.y0) - float(a.y0)) / s)
    dj = round((float(b.x0) - float(a.x0)) / s)
    top, left = min(0, di), min(0, dj)
    bottom = max(za.shape[0], di + zb.shape[0])
    right = max(za.shape[1], dj + zb.shape[1])
    ga = np.full((bottom - top, right - left), np.nan)
    gb = np.full_like(ga, np.nan)
    ga[-top : -top + za.shape[0], -left : -left + za.shape[1]] = za
    gb[di - top : di - top + zb.shape[0], dj - left : dj - left + zb.shape[1]] = zb
    ma, mb = np.isfinite(ga), np.isfinite(gb)
    coverage |= {"gained_cm2": float((mb & ~ma).sum() * cell_cm2),
                 "lost_cm2": float((ma & ~mb).sum() * cell_cm2)}
    both = ma & mb
    if not both.any():
        return None, coverage
    delta = gb[both] - ga[both]
    magnitude = np.abs(delta)
    return {
        "mean": float(delta.mean()),
        "median_abs": float(np.median(magnitude)),
        "p95_abs": float(np.percentile(magnitude, 95)),
        "max_abs": float(magnitude.max()),
        "cells": int(both.sum()),
    }, coverage


def renumbering(a: NumberedLines, b: NumberedLines) -> dict[str, Any]:
    """Peaks and lines whose raster line number differs between two numbered-line records.

    A peak of A is matched with the nearest peak of B in the same pixel column, within one row.
    """
    col_a, row_a = np.asarray(a.col, dtype=np.int64), np.asarray(a.row, dtype=np.float64)
    col_b, row_b = np.asarray(b.col, dtype=np.int64), np.asarray(b.row, dtype=np.float64)
    num_a, num_b = np.asarray(a.number), np.asarray(b.number)
    out: dict[str, Any] = {"peaks_matched": 0, "peaks_renumbered": 0,
                           "peaks_newly_numbered": 0, "peaks_unnumbered": 0,
                           "lines_renumbered": 0, "shifts": {}}
    if col_a.size == 0 or col_b.size == 0:
        return out
    # one sortable key per peak: column first, then row (rows are < 2**20)
    span = float(max(row_a.max(initial=0), row_b.max(initial=0)) + 10.0)
    key_a, key_b = col_a * span + row_a, col_b * span + row_b
    order = np.argsort(key_b, kind="stable")
    sorted_b = key_b[order]
    pos = np.searchsorted(sorted_b, key_a)
    best = np.full(key_a.shape, -1)
    best_d = np.full(key_a.shape, np.inf)
    for candidate in (pos - 1, pos):
        ok = (candidate >= 0) & (candidate < sorted_b.size)
        idx = order[np.clip(candidate, 0, sorted_b.size - 1)]
        d = np.where(ok & (col_b[idx] == col_a), np.abs(row_b[idx] - row_a), np.inf)
        better = d < best_d
        best[better], best_d[better] = idx[better], d[better]
    matched = best_d <= 1.0
    na, nb = num_a[matched], num_b[best[matched]]
    numbered = (na >= 0) & (nb >= 0)
    moved = numbered & (na != nb)
    out |= {
        "peaks_matched": int(matched.sum()),
        "peaks_renumbered": int(moved.sum()),
        "peaks_newly_numbered": int(((na < 0) & (nb >= 0)).sum()),
        "peaks_unnumbered": int(((na >= 0) & (nb < 0)).sum()),
    }
    shifts: dict[int, int] = {}
    for number in np.unique(na[numbered]):
        mine = numbered & (na == number)
        values, counts = np.unique(nb[mine], return_counts=True)
        majority = int(values[np.argmax(counts)])
        if majority != int(number):
            out["lines_renumbered"] += 1
            shifts[majority - int(number)] = shifts.get(majority - int(number), 0) + 1
    out["shifts"] = {str(k): v for k, v in sorted(shifts.items())}
    return out


def parameter_shifts(a: BackShape, b: BackShape) -> dict[str, dict[str, Any]]:
    """Each clinical parameter of two analyses: ``a``, ``b``, ``shift`` (B - A), ``unit``."""
    table_a = a.parameter_table()
    table_b = b.parameter_table()
    out = {}
    for name in sorted(set(table_a) | set(table_b)):
        va = _number(table_a.get(name, {}).get("value"))
        vb = _number(table_b.get(name, {}).get("value"))
        unit = (table_b.get(name) or table_a.get(name) or {}).get("unit", "")
        out[name] = {"a": va, "b": vb, "unit": unit,
                     "shift": None if va is None or vb is None else vb - va}
    return out


def _number(value: Any) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if np.isfinite(number) else None


def diff_records(uid: str, changed: list[str], a: dict[str, Record],
                 b: dict[str, Record]) -> AcquisitionDiff:
    """The measures of one changed acquisition from its records by record kind.

    Parameters
    ----------
    uid : str
        The acquisition.
    changed : list of str
        Stage kinds whose output differs.
    a, b : dict of str to Record
        Records of chain A and B by record kind (``surface``, ``numbered-lines``,
        ``backshape``); a kind missing from either is not measured.
    """
    result = AcquisitionDiff(uid, "changed", changed)
    # by record kind, so a third-party stage making these records is measured the same way
    if isinstance(sa := a.get("surface"), Surface) and isinstance(sb := b.get("surface"), Surface):
        result.displacement, result.coverage = surface_displacement(sa, sb)
    na, nb = a.get("numbered-lines"), b.get("numbered-lines")
    if isinstance(na, NumberedLines) and isinstance(nb, NumberedLines):
        result.numbering = renumbering(na, nb)
    ba, bb = a.get("backshape"), b.get("backshape")
    if isinstance(ba, BackShape) and isinstance(bb, BackShape):
        result.parameters = parameter_shifts(ba, bb)
    return result


# --- over a selection ----------------------------------------------------------------------------

#: Record kinds read to measure a change (the others are only compared by checksum).
MEASURED = ("surface", "numbered-lines", "backshape")


def _paths(rows: list[ResultRow], patterns: dict[str, list[StepPattern]]
           ) -> dict[str, ResultRow] | None:
    """Per stage kind, the results of every target; None when a target has none."""
    out: dict[str, ResultRow] = {}
    for steps in patterns.values():
        path = match_path(rows, steps)
        if path is None:
            return None
        for kind, row in path.items():
            out.setdefault(kind, row)
    return out


def diff_chains(
    archive: Archive,
    chain_a: ChainSpec,
    chain_b: ChainSpec,
    acquisitions: Sequence[tuple[str, int | None]],
    *,
    targets: Sequence[str] = DEFAULT_TARGETS,
    registry: Registry | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ChainDiff:
    """Compare the stored results of two chains over ``acquisitions``.

    Parameters
    ----------
    archive : Archive
        The archive.
    chain_a, chain_b : ChainSpec
        The chains (A: before, B: after).
    acquisitions : sequence of (str, int or None)
        ``(uid, acquisition id)`` as :func:`rasterserver.processing_jobs.resolve_selection`
        gives them; an unknown uid (id None) is reported ``missing-a``.
    targets : sequence of str
        Last stage kinds whose chains are compared (default: mesh and analysis).
    registry : Registry, optional
        Where plugins are found (resolving the chains, reading records).
    progress : callable, optional
        Called with ``(done, total)`` after each acquisition.

    Returns
    -------
    ChainDiff
    """
    from rasterserver.store.derived import DerivedStore

    registry = registry or get_registry()
    patterns_a = {t: chain_a.patterns(t, registry=registry) for t in targets}
    patterns_b = {t: chain_b.patterns(t, registry=registry) for t in targets}
    store = DerivedStore(archive.settings.archive, resolve=registry.record_type)
    report = progress or (lambda _done, _total: None)
    diffs: list[AcquisitionDiff] = []
    total = len(acquisitions)
    for start in range(0, total, 200):  # memory stays bounded: rows of 200 acquisitions
        chunk = acquisitions[start : start + 200]
        with archive.session() as s:
            rows = result_rows(s, [i for _uid, i in chunk if i is not None])
        for uid, acquisition_id in chunk:
            mine = rows.get(acquisition_id, []) if acquisition_id is not None else []
            diffs.append(_diff_one(uid, mine, patterns_a, patterns_b, store))
            report(len(diffs), total)
    from rasterserver.chain_spec import describe_patterns

    return ChainDiff(chain_a.text, chain_b.text, list(targets), describe_patterns(patterns_a),
                     describe_patterns(patterns_b), diffs)


def _diff_one(uid: str, rows: list[ResultRow], patterns_a: dict[str, list[StepPattern]],
              patterns_b: dict[str, list[StepPattern]], store: Any) -> AcquisitionDiff:
    path_a = _paths(rows, patterns_a)
    if path_a is None:
        return AcquisitionDiff(uid, "missing-a")
    path_b = _paths(rows, patterns_b)
    if path_b is None:
        return AcquisitionDiff(uid, "missing-b")
    changed = [kind for kind, row in path_b.items()
               if kind in path_a and path_a[kind].output_checksum != row.output_checksum]
    if not changed:
        return AcquisitionDiff(uid, "unchanged")

    def records(path: dict[str, ResultRow]) -> dict[str, Record]:
        return {row.record_kind: store.read(row.store_path, expected_checksum=row.output_checksum)
                for row in path.values() if row.record_kind in MEASURED}

    return diff_records(uid, changed, records(path_a), records(path_b))
