"""The human side of ``rasterserver compare``'s folder: ``trends.png`` and ``report.html``
(timeline of the visits, their landmark frames, parameter trends, the maps)."""

from __future__ import annotations

import datetime as dt
import html
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rasterserver.analysis import KEY_PARAMETERS, parameter_label
from rasterserver.trends import REPEATABILITY_SOURCE

if TYPE_CHECKING:
    # the service imports this module: the visits' type only for annotations
    from rasterserver.visit_comparison import ArchivedVisit


def write_trends_plot(table: list[dict[str, Any]], path: Path) -> None:
    """``trends.png``: one panel per key parameter over the visits, flagged changes circled."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from rasterserver.output_files import output_file

    rows = [r for r in table if r["parameter"] in KEY_PARAMETERS]
    n = max(len(rows), 1)
    fig = Figure(figsize=(9.0, 2.0 * ((n + 1) // 2)), dpi=100)
    FigureCanvasAgg(fig)
    for k, row in enumerate(rows):
        ax = fig.add_subplot((n + 1) // 2, 2, k + 1)
        dates = [dt.datetime.fromisoformat(v["date"]) for v in row["visits"]]
        values = [np.nan if v["value"] is None else v["value"] for v in row["visits"]]
        # matplotlib's stubs take no datetimes; its unit converters plot them (a date axis)
        ax.plot(dates, values, "o-", color="#1f4e79")  # type: ignore[arg-type]
        for d, v, visit in zip(dates, values, row["visits"], strict=True):
            if visit["flagged"]:
                ax.plot(d, v, "o", color="#c00000", markersize=9, fillstyle="none")  # type: ignore[arg-type]
        ax.set_title(f"{parameter_label(row['parameter'])} ({row['unit']})", fontsize=9)
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    with output_file(path, what="trends plot") as temp:
        fig.savefig(temp, format="png", bbox_inches="tight")


def frames_section(visits: Sequence[ArchivedVisit]) -> list[str]:
    """The landmark frames of the visits: VP, DL, DR, DM and the body-fixed axes (world mm of
    each visit's calibration), the frames the registrations start from."""
    e = html.escape
    out = [
        "<h2>Landmark frames</h2><p>Each visit's landmarks and body-fixed frame (Drerup &amp; "
        "Hierholzer 1987: origin DM; axes transverse, vertical DM → VP, sagittal), in the world "
        "frame of its calibration (mm): the registration of a later visit starts by putting its "
        "frame onto the earlier one's.</p>",
        "<table><tr><th>visit</th><th>VP</th><th>DL</th><th>DR</th><th>DM</th>"
        "<th>transverse</th><th>vertical</th><th>sagittal</th></tr>",
    ]

    def point(p: Any) -> str:
        if p is None or not np.all(np.isfinite(p)):
            return "–"
        return "(" + ", ".join(f"{v:.1f}" for v in p) + ")"

    def axis(a: Any) -> str:
        if not np.all(np.isfinite(a)):
            return "–"
        return "(" + ", ".join(f"{v:+.3f}" for v in a) + ")"

    for v in visits:
        if v.visit is None:
            out.append(
                f"<tr><td>{v.acquired_at:%Y-%m-%d}</td><td colspan='7' style='text-align:left'>"
                f"{e(v.reason)}</td></tr>"
            )
            continue
        shape = v.visit.shape
        cells = "".join(f"<td>{point(shape.landmark(n))}</td>" for n in ("VP", "DL", "DR", "DM"))
        axes = np.asarray(shape.frame_axes, dtype=float)
        cells += "".join(f"<td>{axis(axes[k])}</td>" for k in range(3))
        out.append(f"<tr><td>{v.acquired_at:%Y-%m-%d}</td>{cells}</tr>")
    out.append("</table>")
    return out


def write_report(
    folder: Path,
    visits: Sequence[ArchivedVisit],
    pairs: list[dict[str, Any]],
    table: list[dict[str, Any]],
    asymmetry: dict[str, Any],
    carried: dict[str, Any] | None = None,
) -> None:
    """``report.html`` in ``folder``: the timeline, the frames, the trends and the maps
    (``carried``: :func:`rasterserver.carried_analysis.carried_parameters`)."""
    e = html.escape
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>Comparison of visits</title>",
        "<style>body{font-family:sans-serif;margin:2em}td,th{padding:2px 8px;text-align:right}"
        ".flag{color:#c00000;font-weight:bold}img{max-width:48%;margin:4px}</style></head><body>",
        "<h1>Comparison of visits</h1>",
        "<p>Positions in the world frame of the first visit's calibration (mm, X to the "
        "patient's right, Y down, Z anterior). Distance maps: later visit minus earlier, "
        "positive = posterior (towards the camera).</p>",
        "<h2>Timeline</h2><table><tr><th>visit</th><th>date</th><th>acquisition</th>"
        "<th>analysis</th></tr>",
    ]
    for k, v in enumerate(visits):
        state = "analysed" if v.visit is not None else e(v.reason)
        got = (carried or {}).get(v.uid, {})
        if "from" in got:
            state += f"; VP carried from {e(got['from'])}"
        elif "refused" in got:
            state += f"; VP not found, not carried: {e(got['refused'])}"
        parts.append(
            f"<tr><td>{k + 1}</td><td>{v.acquired_at:%Y-%m-%d}</td><td>{e(v.uid)}</td>"
            f"<td>{state}</td></tr>"
        )
    parts.append("</table><h2>Parameter trends</h2><img src='trends.png' alt='trends'>")
    parts.append(
        "<p>Flagged (red) only when a change exceeds the smallest detectable change "
        "SDC = 1.96·√2·SD; SD source: " + e(REPEATABILITY_SOURCE) + "</p>"
    )
    head = "".join(f"<th>{v.acquired_at:%Y-%m-%d}</th>" for v in visits)
    parts.append(f"<table><tr><th>parameter</th>{head}<th>SDC</th><th>unit</th></tr>")
    for row in table:
        cells = "".join(
            f"<td class='{'flag' if c['flagged'] else ''}'>"
            + ("–" if c["value"] is None else f"{c['value']:.1f}")
            + ("*" if c.get("vp_carried_from") else "")
            + "</td>"
            for c in row["visits"]
        )
        limit = "–" if row["sdc"] is None else f"{row['sdc']:.1f}"
        parts.append(
            f"<tr><td style='text-align:left'>{e(parameter_label(row['parameter']))}</td>"
            f"{cells}<td>{limit}</td><td>{e(row['unit'])}</td></tr>"
        )
    if any(c.get("vp_carried_from") for row in table for c in row["visits"]):
        parts.append(
            "</table><p>* measured along the symmetry line from VP carried from another "
            "visit through their registration (this visit's own VP was not found); what "
            "measures VP's own position is not given with it.</p><table>"
        )
    parts.append("</table><h2>Distance maps</h2>")
    for p in pairs:
        label = f"{e(p['a'])} → {e(p['b'])}"
        if "refused" in p:
            parts.append(f"<p>{label}: not compared: {e(p['refused'])}</p>")
            continue
        s, r = p["distance"], p["registration"]
        parts.append(
            f"<h3>{label}</h3><p>registration: fitness {r['fitness']:.2f}, residual "
            f"{r['rmse_mm']:.2f} mm"
            + (
                f" ({e(r['landmark_start_from'])})"
                if "found" in r.get("landmark_start_from", "")  # frames without VP
                else ""
            )
            + f"; distance rms {s['rms_mm']:.2f} mm, largest "
            f"{s['max_abs_mm']:.1f} mm; area beyond ±2 mm "
            f"{(s['area_above_2mm_mm2'] + s['area_below_minus_2mm_mm2']) / 100:.0f} cm²"
            + (
                f"; not compared (arms, hands or clothing placed otherwise): "
                f"{100 * s['displaced']:.0f} % of the trunk"
                if s.get("displaced")
                else ""
            )
            + "</p>"
            f"<img src='{e(p['files'][1])}' alt='distance map'>"
        )
    parts.append("<h2>Asymmetry maps (Komeili et al. 2015)</h2>")
    for uid, entry in asymmetry.items():
        if "file" in entry:
            parts.append(f"<img src='{e(entry['file'])}' alt='asymmetry {e(uid)}'>")
        else:
            parts.append(f"<p>{e(uid)}: {e(entry.get('refused', ''))}</p>")
    parts += frames_section(visits)
    parts.append("</body></html>")
    (folder / "report.html").write_text("\n".join(parts), encoding="utf-8")
