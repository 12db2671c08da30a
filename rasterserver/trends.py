"""Parameter trends of a patient over visits, with the smallest detectable change.

Every parameter of the back-shape analysis (the ``parameters`` of
:meth:`rasterserver.analysis.Analysis.document`) over all visits of one patient, as a table
(one row per parameter and visit), CSV and JSON. A change between two visits is *flagged*
only when it exceeds the parameter's smallest detectable change

    SDC = 1.96 · √2 · SD

(the 95 % limit of the difference of two measurements each with repeatability SD), where SD
is the one place the comparison takes measurement noise from: :data:`REPEATABILITY_SD`.
A parameter without an SD there is reported but never flagged.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rasterserver.output_files import output_file

__all__ = [
    "REPEATABILITY_SD",
    "REPEATABILITY_SOURCE",
    "TrendVisit",
    "sdc",
    "trends",
    "trends_csv",
    "trends_document",
    "write_trends",
]

#: Where :data:`REPEATABILITY_SD` comes from.
REPEATABILITY_SOURCE = (
    "benchmarks/analysis.py --count 0 --repeat-backs 10 --repeats 10 (analysis code "
    "'analysis.back-shape 1'): 10 tuning backs (the 3 presets and random seeds 0-6) x 10 "
    "simulated acquisitions, independent noise and posture sway up to +-5 mm and +-1 deg; the "
    "pooled within-back SD (root mean of the 10 variances, 90 degrees of freedom), rounded up "
    "to 0.01. Simulated acquisitions: a clinic's own repeatability (patients re-positioned, "
    "breathing) is larger and should replace these values when measured."
)

#: Repeatability standard deviation of every parameter (its unit: mm or deg), from
#: :data:`REPEATABILITY_SOURCE`. The one place the comparison takes measurement noise from.
REPEATABILITY_SD: dict[str, float] = {
    "trunk_length": 0.34,
    "trunk_inclination_mm": 4.71,
    "trunk_inclination_deg": 0.60,
    "trunk_imbalance_mm": 4.88,
    "trunk_imbalance_deg": 0.63,
    "pelvic_tilt_mm": 1.10,
    "pelvic_tilt_deg": 0.63,
    "pelvic_torsion_deg": 0.48,
    "pelvic_rotation_deg": 0.52,
    "kyphotic_angle_deg": 0.41,
    "lordotic_angle_deg": 0.47,
    "fleche_cervicale_mm": 1.66,
    "fleche_lombaire_mm": 2.26,
    "surface_rotation_rms_deg": 0.33,
    "surface_rotation_max_deg": 0.59,
    "surface_rotation_pos_max_deg": 0.51,
    "surface_rotation_neg_max_deg": 0.41,
    "lateral_deviation_rms_mm": 0.34,
    "lateral_deviation_max_mm": 0.63,
    "lateral_deviation_pos_max_mm": 0.54,
    "lateral_deviation_neg_max_mm": 0.54,
    "scoliosis_angle_deg": 0.73,
}

_SDC_FACTOR = 1.96 * math.sqrt(2.0)


def sdc(name: str, sd: Mapping[str, float] = REPEATABILITY_SD) -> float | None:
    """The smallest detectable change of parameter ``name`` (its unit), None if unknown."""
    value = sd.get(name)
    return None if value is None else _SDC_FACTOR * float(value)


@dataclass(frozen=True)
class TrendVisit:
    """One visit's parameters.

    Attributes
    ----------
    label : str
        The acquisition (uid) or another name of the visit.
    when : datetime.datetime or None
        When it was acquired.
    parameters : mapping or None
        ``{name: {"value", "unit", "spread"}}`` of its analysis document; None when it could
        not be analysed.
    """

    label: str
    when: dt.datetime | None
    parameters: Mapping[str, Mapping[str, Any]] | None


def _carried_from(visit: TrendVisit, name: str) -> str | None:
    """The visit whose VP a value was measured with, when not the visit's own."""
    entry = (visit.parameters or {}).get(name) or {}
    source = entry.get("vp_carried_from")
    return str(source) if source else None


def _value(visit: TrendVisit, name: str) -> float | None:
    entry = (visit.parameters or {}).get(name)
    value = entry.get("value") if entry else None
    if not isinstance(value, int | float) or not math.isfinite(float(value)):
        return None
    return float(value)


def trends(
    visits: Sequence[TrendVisit], *, sd: Mapping[str, float] = REPEATABILITY_SD
) -> list[dict[str, Any]]:
    """Every parameter over the visits, with changes and flags.

    Parameters
    ----------
    visits : sequence of TrendVisit
        The patient's visits, in time order.
    sd : mapping, optional
        Repeatability SD per parameter (:data:`REPEATABILITY_SD`).

    Returns
    -------
    list of dict
        One per parameter (clinical order): ``parameter``, ``unit``, ``sd``, ``sdc``,
        ``visits`` (per visit: ``label``, ``date``, ``value``, ``change`` from the previous
        visit with a value, ``flagged``: ``|change| > sdc``, ``vp_carried_from``: the visit
        whose VP the value was measured with when it is not the visit's own, else None),
        ``first_to_last`` (``change``, ``flagged``) and ``flagged`` (any).
    """
    from rasterserver.analysis import ordered_parameters

    names: dict[str, str] = {}
    for v in visits:
        for name, entry in (v.parameters or {}).items():
            names.setdefault(name, str(entry.get("unit", "")))
    out = []
    for name in ordered_parameters(names):
        limit = sdc(name, sd)
        rows, previous, first = [], None, None
        for v in visits:
            value = _value(v, name)
            change: float | None = None if value is None or previous is None else value - previous
            rows.append(
                {
                    "label": v.label,
                    "date": None if v.when is None else v.when.isoformat(),
                    "value": value,
                    "change": change,
                    "flagged": bool(
                        limit is not None and change is not None and abs(change) > limit
                    ),
                    "vp_carried_from": _carried_from(v, name),
                }
            )
            if value is not None:
                previous = value
                first = value if first is None else first
        total = None if first is None or previous is None or len(visits) < 2 else previous - first
        overall = {
            "change": total,
            "flagged": bool(limit is not None and total is not None and abs(total) > limit),
        }
        out.append(
            {
                "parameter": name,
                "unit": names[name],
                "sd": sd.get(name),
                "sdc": limit,
                "visits": rows,
                "first_to_last": overall,
                "flagged": overall["flagged"] or any(r["flagged"] for r in rows),
            }
        )
    return out


def trends_csv(table: Sequence[Mapping[str, Any]]) -> str:
    """The trends as CSV: one row per parameter and visit (``parameter, unit, visit, date,
    value, change, sdc, flagged, vp_carried_from``); empty cells for missing values."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(
        [
            "parameter",
            "unit",
            "visit",
            "date",
            "value",
            "change",
            "sdc",
            "flagged",
            "vp_carried_from",
        ]
    )

    def cell(value: float | None) -> str:
        return "" if value is None else f"{value:.4g}"

    for row in table:
        for v in row["visits"]:
            writer.writerow(
                [
                    row["parameter"],
                    row["unit"],
                    v["label"],
                    v["date"] or "",
                    cell(v["value"]),
                    cell(v["change"]),
                    cell(row["sdc"]),
                    "yes" if v["flagged"] else "",
                    v.get("vp_carried_from") or "",
                ]
            )
    return buffer.getvalue()


def trends_document(table: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The ``trends.json`` document (``rasterserver.trends/1``): the table with the SD source."""
    return {
        "format": "rasterserver.trends/1",
        "sdc": "1.96 * sqrt(2) * SD",
        "sd_source": REPEATABILITY_SOURCE,
        "parameters": list(table),
    }


def write_trends(table: Sequence[Mapping[str, Any]], folder: Path) -> tuple[Path, Path]:
    """Write ``trends.csv`` and ``trends.json`` (with the SD source) into ``folder``."""
    csv_path, json_path = folder / "trends.csv", folder / "trends.json"
    with output_file(csv_path, what="trends table") as temp:
        temp.write_text(trends_csv(table), encoding="utf-8")
    document = trends_document(table)
    with output_file(json_path, what="trends document") as temp:
        temp.write_text(json.dumps(document, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return csv_path, json_path
