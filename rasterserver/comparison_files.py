"""Files of a comparison: distance maps as PLY meshes and as colour-mapped PNG pictures.

The PLY is binary little-endian with, per vertex, ``x y z`` (mm, visit A's world frame),
``nx ny nz`` and the value twice, under the two names the common viewers pick up without
conversion: ``quality`` (MeshLab's per-vertex quality: *Render → Color → Per Vertex Quality*,
checked with pymeshlab in the tests) and ``scalar_<name>`` (the prefix CloudCompare gives the
scalar fields it writes, and loads back as a scalar field). Vertices without a value (no
counterpart on the other visit) and their triangles are left out, so every stored value is
a measurement. The header's comments name the frame, the unit and what the value is.

The PNG shows the map seen from behind (the patient's right on the right, head up) with a
diverging colour map (red: posterior / grown towards the camera, blue: anterior), limits
symmetric about 0 and a scale bar in mm. matplotlib is imported only when a picture is drawn.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rasterserver.comparison import DistanceMap
from rasterserver.output_files import output_file

if TYPE_CHECKING:
    from matplotlib.cm import ScalarMappable
    from matplotlib.figure import Figure

__all__ = ["colour_limit", "distance_png", "write_distance_ply", "write_distance_png"]


def _measured(dmap: DistanceMap) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    keep = np.isfinite(dmap.distance)
    index = np.full(len(keep), -1, dtype=np.int64)
    index[keep] = np.arange(int(keep.sum()))
    tri = (
        dmap.triangles[np.all(keep[dmap.triangles], axis=1)]
        if len(dmap.triangles)
        else (np.zeros((0, 3), dtype=np.int64))
    )
    return dmap.vertices[keep], dmap.normals[keep], dmap.distance[keep], index[tri]


def write_distance_ply(
    dmap: DistanceMap, path: Path | str, *, name: str = "distance", comments: Sequence[str] = ()
) -> Path:
    """Write a distance map as a binary PLY mesh with a per-vertex scalar field.

    Parameters
    ----------
    dmap : DistanceMap
        The map.
    path : Path or str
        The file (written whole through a temporary file, or not at all).
    name : str, optional
        Scalar field name for CloudCompare (``scalar_<name>``).
    comments : sequence of str, optional
        Extra header comments (frame, visits); one line each, no patient data.

    Returns
    -------
    Path
    """
    vertices, normals, values, triangles = _measured(dmap)
    vertex = np.empty(
        len(vertices),
        dtype=[(c, "<f4") for c in ("x", "y", "z", "nx", "ny", "nz", "quality", f"scalar_{name}")],
    )
    for k, c in enumerate("xyz"):
        vertex[c] = vertices[:, k]
        vertex[f"n{c}"] = normals[:, k]
    vertex["quality"] = values
    vertex[f"scalar_{name}"] = values
    face = np.empty(len(triangles), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"] = 3
    face["v"] = triangles
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [
        f"comment {c}".replace("\n", " ")
        for c in (
            f"rasterserver {dmap.what}",
            "unit mm; frame: world frame of visit A's calibration (X right, Y down, Z anterior)",
            *comments,
        )
    ]
    lines += [f"element vertex {len(vertex)}"]
    lines += [f"property float {c}" for c in vertex.dtype.names or ()]
    lines += [f"element face {len(face)}", "property list uchar int vertex_indices", "end_header"]
    header = ("\n".join(lines) + "\n").encode("ascii", errors="replace")
    with output_file(path, what="distance map") as temp, open(temp, "wb") as fh:
        fh.write(header)
        fh.write(vertex.tobytes())
        fh.write(face.tobytes())
    return Path(path)


def colour_limit(values: np.ndarray, *, floor: float = 2.0) -> float:
    """Symmetric colour limit (mm): the 99th percentile of ``|values|``, at least ``floor``,
    rounded up to a whole millimetre (so maps of one patient often share it)."""
    finite = np.abs(values[np.isfinite(values)])
    top = float(np.percentile(finite, 99)) if finite.size else 0.0
    return float(np.ceil(max(top, floor)))


def write_distance_png(
    dmap: DistanceMap,
    path: Path | str,
    *,
    title: str = "",
    limit: float | None = None,
    landmarks: dict[str, np.ndarray] | None = None,
) -> Path:
    """Draw a distance map seen from behind, with a diverging colour scale bar.

    Parameters
    ----------
    dmap : DistanceMap
        The map.
    path : Path or str
        The PNG file (written whole or not at all).
    title : str, optional
        Title above the map.
    limit : float, optional
        Colour limit (mm), symmetric about 0; :func:`colour_limit` of the values by default.
    landmarks : dict of str to numpy.ndarray, optional
        Points (A's world mm) to mark and name on the map.

    Returns
    -------
    Path
    """
    fig = _draw_distance(dmap, title=title, limit=limit, landmarks=landmarks)
    with output_file(path, what="distance map picture") as temp:
        fig.savefig(temp, format="png")
    return Path(path)


def _on_grid(
    vertices: np.ndarray, values: np.ndarray
) -> tuple[np.ma.MaskedArray, tuple[float, float, float, float]] | None:
    """The values as an image when the vertices' (x, y) lie on a square lattice (a mesh
    made from a height-field grid, as the pipeline's are), with the image's extent; None
    otherwise."""
    if len(vertices) < 4:
        return None
    xs = np.unique(np.round(vertices[:, 0], 6))
    steps = np.diff(xs)
    if steps.size == 0:
        return None
    step = float(steps.min())
    if step <= 0:
        return None
    x0, y0 = float(vertices[:, 0].min()), float(vertices[:, 1].min())
    fj = (vertices[:, 0] - x0) / step
    fi = (vertices[:, 1] - y0) / step
    j, i = np.rint(fj).astype(np.int64), np.rint(fi).astype(np.int64)
    if max(np.abs(fj - j).max(), np.abs(fi - i).max()) > 1e-3 or max(i.max(), j.max()) > 4000:
        return None
    picture = np.full((i.max() + 1, j.max() + 1), np.nan)
    picture[i, j] = values
    half = step / 2.0
    extent = (x0 - half, x0 + step * j.max() + half, y0 - half, y0 + step * i.max() + half)
    return np.ma.masked_invalid(picture), extent


def _draw_distance(
    dmap: DistanceMap,
    *,
    title: str,
    limit: float | None,
    landmarks: dict[str, np.ndarray] | None,
) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure
    from matplotlib.tri import Triangulation

    vertices, _normals, values, triangles = _measured(dmap)
    lim = colour_limit(values) if limit is None else float(limit)
    fig = Figure(figsize=(5.6, 5.8), dpi=110)
    FigureCanvasAgg(fig)
    # fixed margins rather than bbox_inches="tight", which draws the figure twice
    fig.subplots_adjust(left=0.14, right=0.9, bottom=0.09, top=0.94)
    ax = fig.add_subplot(1, 1, 1)
    if dmap.displaced is not None and dmap.displaced.any():
        # drawn beneath the map, so that a reader sees where the visits were not compared
        # rather than an outline that ends
        shown = dmap.vertices[dmap.displaced]
        flat = _on_grid(shown, np.zeros(len(shown)))
        if flat is not None:
            ax.imshow(flat[0], cmap=ListedColormap(["0.8"]), extent=flat[1], origin="lower")
        else:
            ax.plot(shown[:, 0], shown[:, 1], ".", markersize=1, color="0.8", rasterized=True)
        ax.text(
            0.01,
            0.01,
            "grey: not compared (arms, hands or clothing placed otherwise)",
            fontsize=7,
            transform=ax.transAxes,
        )
    grid = _on_grid(vertices, values)
    if grid is not None and len(triangles):
        # the mesh of a height field: drawing it as an image is ten times faster than
        # Gouraud-shading its tens of thousands of triangles, and looks the same
        picture, extent = grid
        image: ScalarMappable = ax.imshow(
            picture,
            cmap="RdBu_r",
            vmin=-lim,
            vmax=lim,
            extent=extent,
            origin="lower",
            interpolation="bilinear",
        )
    elif len(triangles):
        tri = Triangulation(vertices[:, 0], vertices[:, 1], triangles)
        image = ax.tripcolor(
            tri, values, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="gouraud", rasterized=True
        )
    if len(triangles):
        bar = fig.colorbar(image, ax=ax, shrink=0.8, extend="both")
        bar.set_label(f"{dmap.what}; + posterior")
    else:
        ax.text(0.5, 0.5, "no overlap", ha="center", va="center", transform=ax.transAxes)
    for label, point in (landmarks or {}).items():
        if point is not None and np.all(np.isfinite(point)):
            ax.plot(point[0], point[1], "k^" if label == "VP" else "ko", markersize=4)
            ax.annotate(label, (point[0], point[1]), xytext=(4, 2), textcoords="offset points")
    ax.set_aspect("equal")
    ax.invert_yaxis()  # world Y points down: the head at the top
    ax.set_xlabel("X (mm, patient's right →)")
    ax.set_ylabel("Y (mm, down)")
    if title:
        ax.set_title(title, fontsize=10)
    return fig


def distance_png(
    dmap: DistanceMap,
    *,
    title: str = "",
    limit: float | None = None,
    landmarks: dict[str, np.ndarray] | None = None,
) -> bytes:
    """The picture of :func:`write_distance_png` in memory (for the HTTP API).

    Parameters and drawing as :func:`write_distance_png`.

    Returns
    -------
    bytes
        The PNG.
    """
    buffer = io.BytesIO()
    _draw_distance(dmap, title=title, limit=limit, landmarks=landmarks).savefig(
        buffer, format="png"
    )
    return buffer.getvalue()
