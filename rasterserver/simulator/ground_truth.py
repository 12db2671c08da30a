"""Exact ground truth of a rendering: where every raster line centre lies in every column.

A line centre is where the diapositive coordinate ``v`` of the surface point seen along a
pixel column crosses the line's ``v``. Crossings are bracketed on the renderer's samples of
the column ``x = c`` (the exact column line through the pixel centres), then refined by the
Illinois variant of regula falsi on exact rays (double-precision undistortion, double-
precision triangle-plane intersection), to ~1e-6 px.

Also here: saving and loading the ground truth (NPZ or HDF5) with the scene's landmarks,
metadata and the station's calibration JSON.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rasterserver.optics import Station
from rasterserver.simulator.illumination import RasterLight
from rasterserver.simulator.tracing import Tracer

if TYPE_CHECKING:
    from rasterserver.simulator.render import Rendering
    from rasterserver.simulator.scene import Scene

#: ``format`` tag stored in ground-truth files.
GROUND_TRUTH_FORMAT = "rasterserver.ground-truth/1"


@dataclass(frozen=True, eq=False)
class LineRows:
    """Exact image rows of the visible raster line centres, one entry per (column, line).

    Attributes
    ----------
    column : numpy.ndarray
        ``(M,)`` int32 pixel column ``c`` (the crossing lies on ``x = c``).
    number : numpy.ndarray
        ``(M,)`` int64 absolute raster line number.
    row : numpy.ndarray
        ``(M,)`` float64 image row ``y`` of the line centre (pixel-centre convention).
    object_index : numpy.ndarray
        ``(M,)`` int16 index of the scene object the line falls on.
    """

    column: np.ndarray
    number: np.ndarray
    row: np.ndarray
    object_index: np.ndarray

    def __len__(self) -> int:
        return int(self.row.size)

    def line(self, number: int) -> tuple[np.ndarray, np.ndarray]:
        """Columns and rows of one line, sorted by column."""
        sel = np.flatnonzero(self.number == number)
        order = np.argsort(self.column[sel], kind="stable")
        return self.column[sel][order], self.row[sel][order]

    @classmethod
    def empty(cls) -> LineRows:
        """No crossings."""
        return cls(np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int16))


def _evaluate(
    tracer: Tracer, station: Station, columns: np.ndarray, rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact ``v`` of the surface seen through image points; also object, point, normal."""
    o, d = station.camera.rays(np.column_stack([columns, rows]))
    hits = tracer.cast(o, d)
    p = tracer.exact_points(o, d, hits.triangle)
    uv = station.projector.project(p)
    return uv[:, 1], hits.object_index, p, hits.normals, uv


def _evaluate_v(
    tracer: Tracer,
    station: Station,
    columns: np.ndarray,
    rows: np.ndarray,
    triangle: np.ndarray,
    obj: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`_evaluate` (``v`` and object) but rays with a known triangle
    (``triangle >= 0``) are intersected with its plane instead of being cast."""
    o, d = station.camera.rays(np.column_stack([columns, rows]))
    tri = triangle.copy()
    obj_out = obj.copy()
    cast = np.flatnonzero(tri < 0)
    if cast.size:
        hits = tracer.cast(o[cast], d[cast])
        tri[cast] = hits.triangle
        obj_out[cast] = hits.object_index
    p = tracer.exact_points(o, d, tri)
    return station.projector.project(p)[:, 1], obj_out


def find_line_rows(
    tracer: Tracer,
    station: Station,
    *,
    sample_rows: np.ndarray,
    v: np.ndarray,
    object_index: np.ndarray,
    light: RasterLight,
    triangle: np.ndarray | None = None,
    tol: float = 1e-6,
    max_iter: int = 60,
    shadow_epsilon: float = 0.05,
) -> LineRows:
    """Exact rows of the raster line centres visible in every image column.

    Parameters
    ----------
    tracer : Tracer
        The scene.
    station : Station
        Camera, projector, raster.
    sample_rows : numpy.ndarray
        ``(K,)`` increasing rows at which the columns were sampled.
    v : numpy.ndarray
        ``(K, W)`` diapositive ``v`` of the sampled points of column ``x = c``; NaN where the
        sample is not lit by the projector.
    object_index : numpy.ndarray
        ``(K, W)`` scene object hit (-1: none).
    light : RasterLight
        Line lookup for the raster.
    triangle : numpy.ndarray, optional
        ``(K, W)`` global triangle index of the samples. Where both ends of a bracket lie
        on the same triangle the refinement intersects rays with its plane instead of
        casting them (every result is still verified by a final cast).
    tol : float
        Row tolerance (px) of the refinement.
    max_iter : int
        Refinement iterations at most.
    shadow_epsilon : float
        Shadow-ray offset (mm).

    Returns
    -------
    LineRows
    """
    raster = light.raster
    camera = station.camera
    valid = np.isfinite(v) & (object_index >= 0)
    pair = valid[:-1] & valid[1:] & (object_index[:-1] == object_index[1:])
    k_idx, col = np.nonzero(pair)
    if k_idx.size == 0:
        return LineRows.empty()
    va, vb = v[k_idx, col], v[k_idx + 1, col]
    ca = light.count_at_or_below(va)
    cb = light.count_at_or_below(vb)
    n_cross = np.abs(ca - cb)
    has = n_cross > 0
    k_idx, col, ca, cb, n_cross = k_idx[has], col[has], ca[has], cb[has], n_cross[has]
    rep = np.repeat(np.arange(k_idx.size), n_cross)
    first = np.minimum(ca, cb)[rep]
    within = np.arange(rep.size) - np.repeat(np.cumsum(n_cross) - n_cross, n_cross)
    line = first + within  # raster line index crossed
    columns = col[rep].astype(np.float64)
    obj = object_index[k_idx, col][rep]
    r_a = sample_rows[k_idx][rep].astype(np.float64)
    r_b = sample_rows[k_idx + 1][rep].astype(np.float64)
    target = light.positions[line]
    fixed = np.full(columns.size, -1, dtype=np.int64)
    if triangle is not None:
        ta, tb = triangle[k_idx, col][rep], triangle[k_idx + 1, col][rep]
        fixed = np.where(ta == tb, ta, -1)

    both = np.concatenate([r_a, r_b])
    v_ab, o_ab = _evaluate_v(
        tracer,
        station,
        np.concatenate([columns, columns]),
        both,
        np.concatenate([fixed, fixed]),
        np.concatenate([obj, obj]),
    )
    n_c = columns.size
    f_a, f_b = v_ab[:n_c] - target, v_ab[n_c:] - target
    ok = (o_ab[:n_c] == obj) & (o_ab[n_c:] == obj) & (f_a * f_b <= 0)
    keep = np.flatnonzero(ok)
    columns, obj, line, target = columns[keep], obj[keep], line[keep], target[keep]
    fixed = fixed[keep]
    r_a, r_b, f_a, f_b = r_a[keep], r_b[keep], f_a[keep], f_b[keep]
    row = np.where(np.abs(f_a) <= np.abs(f_b), r_a, r_b)
    done = (f_a == 0) | (f_b == 0)
    side = np.zeros(row.size, dtype=np.int8)  # Illinois: which end was kept last time
    for _ in range(max_iter):
        act = np.flatnonzero(~done)
        if act.size == 0:
            break
        a, b, fa, fb = r_a[act], r_b[act], f_a[act], f_b[act]
        r_new = b - fb * (b - a) / (fb - fa)
        bad = ~np.isfinite(r_new) | (r_new <= np.minimum(a, b)) | (r_new >= np.maximum(a, b))
        r_new = np.where(bad, 0.5 * (a + b), r_new)
        v_new, o_new = _evaluate_v(tracer, station, columns[act], r_new, fixed[act], obj[act])
        f_new = v_new - target[act]
        lost = o_new != obj[act]  # an occluding edge inside the bracket: give up on it
        f_new = np.where(lost, np.nan, f_new)
        same_as_b = np.sign(f_new) == np.sign(fb)
        # the new point replaces the end with the same sign; halve the kept end's value if it
        # was kept twice in a row (Illinois), which keeps convergence superlinear
        new_a = np.where(same_as_b, a, r_new)
        new_fa = np.where(same_as_b, np.where(side[act] == 1, fa * 0.5, fa), f_new)
        new_b = np.where(same_as_b, r_new, b)
        new_fb = np.where(same_as_b, f_new, np.where(side[act] == -1, fb * 0.5, fb))
        side[act] = np.where(same_as_b, 1, -1)
        r_a[act], f_a[act], r_b[act], f_b[act] = new_a, new_fa, new_b, new_fb
        row[act] = r_new
        conv = (np.abs(new_b - new_a) < tol) | (f_new == 0) | lost
        conv |= np.abs(f_new) < 1e-10
        done[act] = conv
        row[act[lost]] = np.nan
    # keep converged crossings that are lit by the projector and inside the image
    v_fin, o_fin, p_fin, n_fin, uv_fin = _evaluate(tracer, station, columns, row)
    good = np.isfinite(row) & (o_fin == obj) & (np.abs(v_fin - target) < 1e-4)
    good &= (row >= -0.5) & (row <= camera.height - 0.5)
    good &= station.projector.in_bounds(np.nan_to_num(uv_fin, nan=-1e9))
    to_proj = station.projector.centre[None, :] - p_fin
    good &= np.einsum("ij,ij->i", np.nan_to_num(n_fin.astype(np.float64)), to_proj) > 0
    idx = np.flatnonzero(good)
    occluded = tracer.occluded(
        p_fin[idx], n_fin[idx], station.projector.centre, epsilon=shadow_epsilon
    )
    idx = idx[~occluded]
    order = np.lexsort((row[idx], columns[idx]))
    idx = idx[order]
    return LineRows(
        column=columns[idx].astype(np.int32),
        number=raster.numbers[line[idx]].astype(np.int64),
        row=row[idx],
        object_index=obj[idx].astype(np.int16),
    )


# ---------------------------------------------------------------------- persistence
_ARRAYS = (
    "image",
    "electrons",
    "points",
    "normals",
    "object_index",
    "line_number",
    "diapositive",
    "visible",
    "shadow",
)


def _payload(rendering: Rendering, scene: Scene, station: Station) -> dict[str, Any]:
    arrays: dict[str, np.ndarray] = {name: getattr(rendering, name) for name in _ARRAYS}
    lr = rendering.line_rows
    arrays.update(
        {
            "line_rows/column": lr.column,
            "line_rows/number": lr.number,
            "line_rows/row": lr.row,
            "line_rows/object_index": lr.object_index,
        }
    )
    for name, value in scene.landmarks.items():
        arrays[f"landmarks/{name}"] = np.asarray(value, dtype=np.float64)
    attrs = {
        "format": GROUND_TRUTH_FORMAT,
        "object_names": json.dumps(list(rendering.object_names)),
        "station": station.to_json(indent=None),
        "raster": station.raster_definition.to_json(indent=None),
        "scene_metadata": json.dumps(dict(scene.metadata), default=str),
        "settings": json.dumps(rendering.settings_dict()),
        "seed": str(rendering.seed),
    }
    return {"arrays": arrays, "attrs": attrs}


def save_ground_truth(
    path: str | Path, rendering: Rendering, scene: Scene, station: Station
) -> Path:
    """Write a rendering's image and ground truth to NPZ (``.npz``) or HDF5 (``.h5``).

    Contents: the arrays of :class:`~rasterserver.simulator.render.Rendering` (``image``,
    ``electrons``, ``points``, ``normals``, ``object_index``, ``line_number``,
    ``diapositive``, ``visible``, ``shadow``), ``line_rows/{column,number,row,object_index}``,
    ``landmarks/<name>``, and the text attributes ``format``, ``object_names`` (JSON list),
    ``station`` (calibration JSON), ``raster`` (raster JSON), ``scene_metadata`` (JSON),
    ``settings`` (JSON) and ``seed``. In NPZ the attributes are 0-d string arrays named
    ``attrs/<name>``; in HDF5 they are root attributes.

    Parameters
    ----------
    path : str or Path
        Target file; its suffix picks the format.
    rendering : Rendering
    scene : Scene
    station : Station

    Returns
    -------
    Path
    """
    path = Path(path)
    data = _payload(rendering, scene, station)
    if path.suffix in (".h5", ".hdf5"):
        import h5py

        with h5py.File(path, "w") as f:
            for name, arr in data["arrays"].items():
                kw = {"compression": "gzip", "compression_opts": 4} if arr.ndim >= 2 else {}
                f.create_dataset(name, data=arr, **kw)
            for name, text in data["attrs"].items():
                f.attrs[name] = text
    else:
        flat = dict(data["arrays"])
        flat.update({f"attrs/{k}": np.array(v) for k, v in data["attrs"].items()})
        with path.open("wb") as fh:
            np.savez_compressed(fh, **flat)
    return path


def load_ground_truth(path: str | Path) -> dict[str, Any]:
    """Read a file written by :func:`save_ground_truth`.

    Returns
    -------
    dict
        The arrays by name; ``line_rows`` as :class:`LineRows`; ``landmarks`` as a dict;
        ``station`` as :class:`~rasterserver.optics.Station`; ``raster`` as
        :class:`~rasterserver.raster.Raster`; ``object_names`` (list), ``scene_metadata``
        and ``settings`` (dicts), ``seed`` (int).
    """
    from rasterserver.documents import load_calibration_document, load_raster_document

    path = Path(path)
    arrays: dict[str, np.ndarray] = {}
    attrs: dict[str, str] = {}
    if path.suffix in (".h5", ".hdf5"):
        import h5py

        with h5py.File(path, "r") as f:

            def visit(name: str, obj: Any) -> None:
                if isinstance(obj, h5py.Dataset):
                    arrays[name] = obj[()]

            f.visititems(visit)
            attrs = {k: str(v) for k, v in f.attrs.items()}
    else:
        with np.load(path, allow_pickle=False) as z:
            for name in z.files:
                if name.startswith("attrs/"):
                    attrs[name[len("attrs/") :]] = str(z[name])
                else:
                    arrays[name] = z[name]
    if attrs.get("format") != GROUND_TRUTH_FORMAT:
        raise ValueError(f"{path} is not a {GROUND_TRUTH_FORMAT} file")
    out: dict[str, Any] = {k: v for k, v in arrays.items() if "/" not in k}
    out["line_rows"] = LineRows(
        column=arrays["line_rows/column"],
        number=arrays["line_rows/number"],
        row=arrays["line_rows/row"],
        object_index=arrays["line_rows/object_index"],
    )
    out["landmarks"] = {
        k[len("landmarks/") :]: v for k, v in arrays.items() if k.startswith("landmarks/")
    }
    out["object_names"] = json.loads(attrs["object_names"])
    out["station"] = load_calibration_document(attrs["station"])
    out["raster"] = load_raster_document(attrs["raster"])
    out["scene_metadata"] = json.loads(attrs["scene_metadata"])
    out["settings"] = json.loads(attrs["settings"])
    out["seed"] = int(attrs["seed"])
    return out
