"""The one-page back-shape report of an acquisition (PNG or PDF), as a clinician reads it.

One landscape page, in the manner of a DIERS formetric report: the back as seen from behind
(relief map with the landmarks, the symmetry line and the spinal midline), the curvature map
(mean curvature H: convex red, concave blue), the frontal and sagittal projections of the
midline, the surface rotation along the trunk and the parameter table (mean ± spread over the
frames). Every panel shares the world's vertical axis, so a height reads across the page.

Drawn with matplotlib's object API on the Agg canvas (no pyplot, no global state: several
reports may be drawn at once in the server's threads). matplotlib is imported only here, and
this module only when a report is asked for, so other commands do not pay for it.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rasterserver.analysis import WORLD_FRAME, Analysis, ordered_parameters, parameter_label
from rasterserver.errors import InputError
from rasterserver.records_analysis import LANDMARKS, SAGITTAL_POINTS, BackShape
from rasterserver.records_surface import Surface

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["REPORT_FORMATS", "render_report", "write_report"]

#: File formats of the report, by suffix.
REPORT_FORMATS = ("png", "pdf")

_PAGE_INCHES = (16.5, 9.0)
_DPI = 110
_MARKERS = {"VP": "^", "DL": "o", "DR": "o", "DM": "s", "SP": "D"}
# keyword arguments of Axes.plot
_SYMMETRY: dict[str, Any] = {
    "color": "black",
    "linestyle": "--",
    "linewidth": 1.2,
    "label": "symmetry line",
}
_MIDLINE: dict[str, Any] = {"color": "#c00000", "linewidth": 1.8, "label": "spinal midline"}


def _relief(surface: Surface, shape: BackShape) -> np.ndarray:
    """Depth against the plane fitting the trunk between VP and DM best (mm, + towards the
    camera): the back's shape without its lean, not dominated by the buttocks."""
    z = surface.z
    x, y = surface.coordinates()
    xx, yy = np.meshgrid(x, y)
    valid = np.isfinite(z)
    vp, dm = shape.landmark("VP"), shape.landmark("DM")
    if vp is not None and dm is not None:
        trunk = valid & (yy >= vp[1]) & (yy <= dm[1])
        valid = trunk if trunk.sum() >= 3 else valid
    if valid.sum() < 3:
        return np.full_like(z, np.nan)
    design = np.column_stack([xx[valid], yy[valid], np.ones(valid.sum())])
    coef, *_ = np.linalg.lstsq(design, z[valid], rcond=None)
    return -(z - (coef[0] * xx + coef[1] * yy + coef[2]))


def _extent(
    x0: float, y0: float, spacing: float, shape: tuple[int, ...]
) -> tuple[float, float, float, float]:
    ny, nx = shape[:2]
    half = spacing / 2
    return x0 - half, x0 + (nx - 1) * spacing + half, y0 + (ny - 1) * spacing + half, y0 - half


def _overlay(ax: Axes, shape: BackShape, *, labels: bool) -> None:
    """Landmarks, symmetry line and midline in the frontal view (world X, Y)."""
    if len(shape.symmetry_line):
        ax.plot(shape.symmetry_line[:, 0], shape.symmetry_line[:, 1], **_SYMMETRY)
    if len(shape.midline):
        ax.plot(shape.midline[:, 0], shape.midline[:, 1], **_MIDLINE)
    for name in LANDMARKS:
        point = shape.landmark(name)
        if point is None:
            continue
        ax.plot(
            point[0],
            point[1],
            _MARKERS[name],
            markersize=7,
            markerfacecolor="white",
            markeredgecolor="black",
            markeredgewidth=1.2,
        )
        if labels:
            dx = -14 if name == "DL" else 8
            ax.annotate(
                name,
                (point[0], point[1]),
                xytext=(dx, 4),
                textcoords="offset points",
                fontsize=8,
                fontweight="bold",
                bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8},
            )


def _frontal_deviation(points: np.ndarray, shape: BackShape) -> np.ndarray | None:
    """X distance of ``points`` from the line VP–DM at their height (mm, + to the right)."""
    vp, dm = shape.landmark("VP"), shape.landmark("DM")
    if vp is None or dm is None or abs(dm[1] - vp[1]) < 1e-9 or not len(points):
        return None
    along = (points[:, 1] - vp[1]) / (dm[1] - vp[1])
    return points[:, 0] - (vp[0] + along * (dm[0] - vp[0]))


def _map_panel(
    ax: Axes,
    image: np.ndarray,
    shape: BackShape,
    extent: tuple[float, float, float, float],
    *,
    cmap: str,
    limits: tuple[float, float],
    title: str,
    unit: str,
    figure: Figure,
    contours: bool = False,
) -> None:
    shown = ax.imshow(
        image,
        extent=extent,
        cmap=cmap,
        vmin=limits[0],
        vmax=limits[1],
        interpolation="nearest",
        origin="upper",
    )
    if contours and np.isfinite(image).sum() > 16:
        x = np.linspace(extent[0], extent[1], image.shape[1])
        y = np.linspace(extent[3], extent[2], image.shape[0])
        step = 5.0
        levels = np.arange(np.floor(limits[0] / step) * step, limits[1] + step, step)
        ax.contour(x, y, image, levels=levels, colors="black", linewidths=0.3, alpha=0.5)
    _overlay(ax, shape, labels=True)
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("X (mm)  L ← → R", fontsize=8)
    ax.set_aspect("equal", adjustable="datalim")
    bar = figure.colorbar(shown, ax=ax, orientation="horizontal", fraction=0.04, pad=0.04)
    bar.set_label(unit, fontsize=8)
    bar.ax.tick_params(labelsize=7)


def _profile_panel(ax: Axes, title: str, xlabel: str) -> None:
    ax.set_title(title, fontsize=10)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.axvline(0.0, color="grey", linewidth=0.6)
    ax.grid(True, linewidth=0.3, alpha=0.6)


def _landmark_heights(ax: Axes, shape: BackShape) -> None:
    for name in ("VP", "DM"):
        point = shape.landmark(name)
        if point is not None:
            ax.axhline(point[1], color="grey", linewidth=0.5, linestyle=":")
            ax.text(
                1.0,
                point[1],
                f" {name}",
                transform=ax.get_yaxis_transform(),
                fontsize=7,
                va="center",
                color="grey",
                clip_on=False,
            )


def _value_text(entry: dict[str, Any]) -> str:
    value, spread = entry.get("value"), entry.get("spread")
    if value is None:
        return "–"
    text = f"{round(value, 1) + 0.0:.1f}"  # + 0.0: no "-0.0"
    if spread is not None:
        text += f" ± {spread:.1f}"
    return text


def _table_panel(ax: Axes, document: dict[str, Any]) -> None:
    ax.axis("off")
    parameters = document["parameters"]
    rows = [
        [parameter_label(name), _value_text(parameters[name]), parameters[name]["unit"]]
        for name in ordered_parameters(parameters)
    ]
    if not rows:
        ax.text(0.0, 1.0, "no parameters", va="top", fontsize=9)
        return
    spread = len(document["frames"]) > 1
    table = ax.table(
        cellText=rows,
        colLabels=["parameter", "mean ± spread" if spread else "value", "unit"],
        colWidths=[0.58, 0.28, 0.14],
        loc="upper center",
        cellLoc="left",
    )
    table.auto_set_font_size(False)
    table.set_fontsize(8)
    table.scale(1.0, 1.18)
    for (row, _col), cell in table.get_celld().items():
        cell.set_linewidth(0.3)
        if row == 0:
            cell.set_text_props(fontweight="bold")
            cell.set_facecolor("#e8e8e8")
        elif row % 2 == 0:
            cell.set_facecolor("#f6f6f6")
    ax.set_title("Parameters", fontsize=10)
    reasons = document["reasons"]
    if reasons:
        notes = "\n".join(f"• {r['what']}: {r['why']}" for r in reasons)
        ax.text(
            0.0,
            0.0,
            "Not found or not analysed\n" + notes,
            transform=ax.transAxes,
            fontsize=8,
            va="bottom",
            ha="left",
            wrap=True,
        )


def _figure(analysis: Analysis, header: Sequence[str]) -> Figure:
    from matplotlib.figure import Figure
    from matplotlib.layout_engine import ConstrainedLayoutEngine

    document = analysis.document()
    shown = analysis.shown_frame()
    shape = analysis.combined if len(analysis.frames) == 1 else shown.shape
    # constrained layout, leaving the bottom strip to the footer
    layout = ConstrainedLayoutEngine(rect=(0.0, 0.025, 1.0, 0.975))
    figure = Figure(figsize=_PAGE_INCHES, dpi=_DPI, layout=layout)
    grid = figure.add_gridspec(1, 6, width_ratios=[3.0, 3.0, 1.25, 1.25, 1.25, 3.6])
    relief_ax = figure.add_subplot(grid[0])
    axes = [relief_ax] + [figure.add_subplot(grid[k], sharey=relief_ax) for k in range(1, 5)]
    curvature_ax, frontal_ax, sagittal_ax, rotation_ax = axes[1:]
    table_ax = figure.add_subplot(grid[5])

    # the maps: relief when the surface is at hand, curvature always
    curvature = shape.mean_curvature.astype(np.float64) * 1000.0  # 1/m reads better than 1/mm
    extent = _extent(shape.x0, shape.y0, shape.spacing, curvature.shape)
    surface = shown.surface
    if surface is not None and surface.z.size:
        relief = _relief(surface, shape)
        lo, hi = np.nanpercentile(relief, [1, 99]) if np.isfinite(relief).any() else (-1.0, 1.0)
        _map_panel(
            relief_ax,
            relief,
            shape,
            _extent(surface.x0, surface.y0, surface.spacing, relief.shape),
            cmap="viridis",
            limits=(float(lo), float(hi)),
            contours=True,
            title="Relief, landmarks and lines",
            unit="mm towards the camera (plane removed)",
            figure=figure,
        )
    else:
        relief_ax.text(0.5, 0.5, "surface not loaded", ha="center", transform=relief_ax.transAxes)
        _overlay(relief_ax, shape, labels=True)
        relief_ax.set_title("Landmarks and lines", fontsize=10)
    if curvature.size and np.isfinite(curvature).any():
        bound = float(np.nanpercentile(np.abs(curvature), 98)) or 1.0
        _map_panel(
            curvature_ax,
            curvature,
            shape,
            extent,
            cmap="RdBu_r",
            limits=(-bound, bound),
            title="Mean curvature H",
            unit="1/m (red convex, blue concave)",
            figure=figure,
        )
    else:
        curvature_ax.text(
            0.5, 0.5, "no curvature map", ha="center", transform=curvature_ax.transAxes
        )
    relief_ax.set_ylabel("Y (mm, down)", fontsize=8)

    # the profiles along the trunk, against the same world height
    _profile_panel(frontal_ax, "Frontal", "lateral (mm)  L ← → R")
    for points, style in ((shape.symmetry_line, _SYMMETRY), (shape.midline, _MIDLINE)):
        deviation = _frontal_deviation(points, shape)
        if deviation is not None:
            frontal_ax.plot(deviation, points[:, 1], **style)
    _profile_panel(sagittal_ax, "Sagittal", "Z (mm)  post. ← → ant.")
    reference = shape.landmark("DM")
    z0 = float(reference[2]) if reference is not None else 0.0
    for points, style in ((shape.symmetry_line, _SYMMETRY), (shape.midline, _MIDLINE)):
        if len(points):
            sagittal_ax.plot(points[:, 2] - z0, points[:, 1], **style)
    for name in SAGITTAL_POINTS:  # inflection points and apices of the profile
        point = shape.sagittal_point(name)
        if point is not None:
            sagittal_ax.plot(point[2] - z0, point[1], "o", markersize=4, color="black")
            sagittal_ax.annotate(
                name,
                (point[2] - z0, point[1]),
                xytext=(4, 0),
                textcoords="offset points",
                fontsize=7,
                ha="left",
                va="center",
            )
    sagittal_ax.set_xlabel("Z - Z(DM) (mm)  post. ← → ant.", fontsize=8)
    _profile_panel(rotation_ax, "Surface rotation", "degrees (+: right side back)")
    if len(shape.surface_rotation):
        rotation_ax.plot(
            shape.surface_rotation, shape.symmetry_line[:, 1], color="#1f4e9c", linewidth=1.6
        )
        rotation_ax.fill_betweenx(
            shape.symmetry_line[:, 1], 0.0, shape.surface_rotation, color="#1f4e9c", alpha=0.15
        )
    for ax in (frontal_ax, sagittal_ax, rotation_ax):
        _landmark_heights(ax, shape)
        ax.tick_params(labelsize=7)
        ax.tick_params(axis="y", labelleft=False)
    for ax in (relief_ax, curvature_ax):
        ax.tick_params(labelsize=7)
    curvature_ax.tick_params(axis="y", labelleft=False)
    if frontal_ax.get_legend_handles_labels()[0]:
        frontal_ax.legend(fontsize=7, loc="lower left")
    ys = [p[1] for name in LANDMARKS if (p := shape.landmark(name)) is not None]
    if surface is not None and surface.z.size:
        rows = np.flatnonzero(np.isfinite(surface.z).any(axis=1))
        if rows.size:
            ys += [surface.y0 + rows[0] * surface.spacing, surface.y0 + rows[-1] * surface.spacing]
    if len(shape.symmetry_line):
        ys += [float(shape.symmetry_line[:, 1].min()), float(shape.symmetry_line[:, 1].max())]
    if ys:
        relief_ax.set_ylim(max(ys) + 20.0, min(ys) - 20.0)  # down is down
    _table_panel(table_ax, document)

    heading = [
        "Back-shape analysis",
        "   ·   ".join(line for line in header if line),
        _frames_line(analysis, shown),
    ]
    figure.suptitle(
        "\n".join(line for line in heading if line), fontsize=10, x=0.01, ha="left", linespacing=1.4
    )
    figure.text(0.01, 0.006, _footer(document), fontsize=7, ha="left", va="bottom")
    return figure


def _frames_line(analysis: Analysis, shown: Any) -> str:
    n = len(analysis.frames)
    analysed = sum(f.analysed for f in analysis.frames)
    if n == 1:
        text = f"frame: {shown.name}"
    else:
        text = (
            f"{analysed} of {n} frames analysed (maps and lines: {shown.name}; "
            "parameters: mean ± spread)"
        )
    plugin = analysis.plugin
    if plugin.get("plugin"):
        text += f"   ·   {plugin['plugin']} version {plugin.get('version', '?')}"
    if analysis.calibration:
        text += f"   ·   calibration {analysis.calibration}"
    return text


def _footer(document: dict[str, Any]) -> str:
    frame = document["frame"]
    text = f"Positions in {frame['unit']}, {frame['name']} frame: {WORLD_FRAME['axes']}"
    if frame.get("gravity") is not None:
        text += " (" + ", ".join(f"{v:.3f}" for v in frame["gravity"]) + ")"
    return text + ". Definitions of the parameters: docs/analysis.md."


def render_report(analysis: Analysis, *, header: Sequence[str] = (), fmt: str = "png") -> bytes:
    """Draw the report page of ``analysis`` and return the file's bytes.

    Parameters
    ----------
    analysis : Analysis
        A checked analysis (:meth:`Analysis.check`); its shown frame's surface, when loaded,
        gives the relief map.
    header : sequence of str, optional
        Lines under the title (acquisition, patient, date: what the caller may show).
    fmt : {"png", "pdf"}
        File format.

    Returns
    -------
    bytes

    Raises
    ------
    InputError
        An unknown format, or an analysis that found nothing.
    """
    if fmt not in REPORT_FORMATS:
        raise InputError(f"report format {fmt!r}: use one of {', '.join(REPORT_FORMATS)}")
    analysis.check()
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    figure = _figure(analysis, header)
    buffer = io.BytesIO()
    if fmt == "pdf":
        from matplotlib.backends.backend_pdf import PdfPages

        with PdfPages(
            buffer, metadata={"Title": "Back-shape analysis", "Creator": "rasterserver"}
        ) as pdf:
            pdf.savefig(figure)
    else:
        FigureCanvasAgg(figure)
        figure.savefig(buffer, format="png", dpi=_DPI)
    return buffer.getvalue()


def report_format(path: Path) -> str:
    """The report format a path asks for by its suffix (``.png`` or ``.pdf``).

    Raises
    ------
    InputError
        Another suffix.
    """
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in REPORT_FORMATS:
        raise InputError(
            f"report {path.name}: the report is written as .png or .pdf, not {path.suffix!r}"
        )
    return fmt


def write_report(analysis: Analysis, path: Path, *, header: Sequence[str] = ()) -> Path:
    """Write the report of ``analysis`` to ``path`` (PNG or PDF by its suffix), whole or not
    at all.

    Raises
    ------
    InputError
        A suffix other than ``.png``/``.pdf``, a path that cannot be written, or an analysis
        that found nothing.
    """
    from rasterserver.output_files import check_output, output_file

    path = check_output(Path(path), what="report")
    data = render_report(analysis, header=header, fmt=report_format(path))
    with output_file(path, what="report") as temp:
        temp.write_bytes(data)
    return path
