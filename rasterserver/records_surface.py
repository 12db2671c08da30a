"""Records of the geometric half of the chain: 3-D points, the gridded surface, the mesh.

``numbers → points → surface → mesh`` (stages 5-7). All coordinates are millimetres in the
world frame of the calibration (:mod:`rasterserver.optics`: X right, Y down, Z away from the
camera into the patient), so the back is a height field ``z(x, y)`` seen from the camera.

An empty record is a valid result: when nothing could be reconstructed (no numbered lines,
a raster-free frame) a stage returns arrays of length 0 and says why in ``reason``, so the
caller can show the reason instead of an error or, worse, a plausible-looking nothing.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from rasterserver.errors import InputError
from rasterserver.records import Record

__all__ = ["MeshRecord", "Points", "Surface"]

_POINT_FIELDS: tuple[tuple[str, str], ...] = (
    ("x", "f8"),
    ("y", "f8"),
    ("z", "f8"),
    ("number", "i4"),
    ("col", "i4"),
    ("row", "f8"),
    ("area", "f4"),
)


def _check_1d(owner: str, arrays: dict[str, np.ndarray], dtypes: dict[str, str]) -> int:
    sizes = {name: a.shape for name, a in arrays.items()}
    n = next(iter(sizes.values()))
    for name, array in arrays.items():
        if array.ndim != 1:
            raise InputError(f"{owner}.{name} must be 1-D, got shape {array.shape}")
        if array.shape != n:
            detail = ", ".join(f"{k} {v}" for k, v in sizes.items())
            raise InputError(f"{owner}: per-point arrays differ in length ({detail})")
        if array.dtype != np.dtype(dtypes[name]):
            raise InputError(f"{owner}.{name} must be {np.dtype(dtypes[name])}, not {array.dtype}")
    return int(n[0])


class Points(Record):
    """Reconstructed 3-D surface points, one per raster-line peak (or per smoothed sample).

    Attributes
    ----------
    x, y, z : numpy.ndarray
        ``(N,)`` float64 world coordinates (mm).
    number : numpy.ndarray
        ``(N,)`` int32 absolute raster line number the point lies on.
    col : numpy.ndarray
        ``(N,)`` int32 image column of the peak.
    row : numpy.ndarray
        ``(N,)`` float64 sub-pixel image row of the peak (pixel-centre convention).
    area : numpy.ndarray
        ``(N,)`` float32 peak area (the line's brightness; low on steep surface parts).
    image_shape : numpy.ndarray
        ``(2,)`` int64 ``(rows, columns)`` of the frame the peaks came from.
    reason : str
        Why the record is empty or what was left out (e.g. peaks without a line number);
        empty when there is nothing to say.
    """

    kind: ClassVar[str] = "points"
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    number: np.ndarray
    col: np.ndarray
    row: np.ndarray
    area: np.ndarray
    image_shape: np.ndarray
    reason: str = ""

    def validate(self) -> None:
        """Refuse per-point arrays of different lengths or dtypes, or a bad image shape."""
        _check_1d(
            "Points",
            {name: getattr(self, name) for name, _ in _POINT_FIELDS},
            dict(_POINT_FIELDS),
        )
        if self.image_shape.shape != (2,) or self.image_shape.dtype.kind not in "iu":
            raise InputError(f"Points.image_shape must be 2 integers, got {self.image_shape!r}")

    def __len__(self) -> int:
        return int(self.x.size)

    @property
    def xyz(self) -> np.ndarray:
        """``(N, 3)`` float64 coordinates (a new array)."""
        return np.column_stack([self.x, self.y, self.z])

    @classmethod
    def empty(cls, image_shape: tuple[int, int] | np.ndarray, reason: str) -> Points:
        """A record without points, saying ``reason``.

        Parameters
        ----------
        image_shape : tuple of int or numpy.ndarray
            ``(rows, columns)`` of the frame.
        reason : str
            Why there are no points.

        Returns
        -------
        Points
        """
        arrays = {name: np.zeros(0, dtype=dtype) for name, dtype in _POINT_FIELDS}
        return cls(**arrays, image_shape=np.asarray(image_shape, dtype=np.int64), reason=reason)

    def take(self, index: np.ndarray, *, reason: str | None = None) -> Points:
        """The points selected by ``index`` (indices or a boolean mask), as a new record.

        Parameters
        ----------
        index : numpy.ndarray
            Integer indices or a boolean mask of length ``N``.
        reason : str, optional
            Reason of the new record; the current one when omitted.

        Returns
        -------
        Points
        """
        arrays = {
            name: np.ascontiguousarray(getattr(self, name)[index]) for name, _ in _POINT_FIELDS
        }
        return Points(
            **arrays,
            image_shape=self.image_shape.copy(),
            reason=self.reason if reason is None else reason,
        )


class Surface(Record):
    """The back as a height field ``z(x, y)`` on a regular grid in the world frame.

    Cell ``[i, j]`` is the point ``(x0 + j * spacing, y0 + i * spacing, z[i, j])``. Grid
    origins are multiples of ``spacing``, so grids of different acquisitions line up.

    Attributes
    ----------
    x0, y0 : float
        World ``x`` of column 0 and ``y`` of row 0 (mm).
    spacing : float
        Grid step (mm), the same in x and y.
    z : numpy.ndarray
        ``(ny, nx)`` float64 depth (mm); NaN where the surface was not measured.
    count : numpy.ndarray or None
        ``(ny, nx)`` int32 number of smoothed samples falling into each cell.
    weight : numpy.ndarray or None
        ``(ny, nx)`` float32 confidence in [0, 1] of each cell, plugin-defined.
    samples : numpy.ndarray or None
        ``(M, 3)`` float64 smoothed points the grid was interpolated from (the seed's
        ≈ 8,000 points used for shape analysis).
    sample_number, sample_col : numpy.ndarray or None
        ``(M,)`` int32 line number and (centre) image column of each sample.
    sample_row : numpy.ndarray or None
        ``(M,)`` float64 mean image row of each sample.
    sample_area : numpy.ndarray or None
        ``(M,)`` float32 mean peak area of each sample.
    reason : str
        Why the surface is empty, or a note; empty when there is nothing to say.
    """

    kind: ClassVar[str] = "surface"
    x0: float
    y0: float
    spacing: float
    z: np.ndarray
    count: np.ndarray | None = None
    weight: np.ndarray | None = None
    samples: np.ndarray | None = None
    sample_number: np.ndarray | None = None
    sample_col: np.ndarray | None = None
    sample_row: np.ndarray | None = None
    sample_area: np.ndarray | None = None
    reason: str = ""

    def validate(self) -> None:
        """Refuse a non-positive spacing, a non-2-D grid or mismatched companion arrays."""
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise InputError(f"Surface.spacing must be positive, got {self.spacing}")
        if not (np.isfinite(self.x0) and np.isfinite(self.y0)):
            raise InputError("Surface.x0 and y0 must be finite")
        if self.z.ndim != 2 or self.z.dtype != np.float64:
            raise InputError(
                f"Surface.z must be a 2-D float64 grid, got {self.z.dtype} {self.z.shape}"
            )
        for name in ("count", "weight"):
            grid = getattr(self, name)
            if grid is not None and grid.shape != self.z.shape:
                raise InputError(f"Surface.{name} has shape {grid.shape}, z has {self.z.shape}")
        if self.samples is not None:
            if self.samples.ndim != 2 or self.samples.shape[1] != 3:
                raise InputError(f"Surface.samples must be (M, 3), got {self.samples.shape}")
            m = self.samples.shape[0]
            for name in ("sample_number", "sample_col", "sample_row", "sample_area"):
                extra = getattr(self, name)
                if extra is not None and extra.shape != (m,):
                    raise InputError(f"Surface.{name} must have shape ({m},), got {extra.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape ``(ny, nx)``."""
        return int(self.z.shape[0]), int(self.z.shape[1])

    @property
    def valid(self) -> np.ndarray:
        """``(ny, nx)`` bool: cells holding a depth."""
        return np.isfinite(self.z)

    def coordinates(self) -> tuple[np.ndarray, np.ndarray]:
        """World ``x`` of the columns ``(nx,)`` and ``y`` of the rows ``(ny,)`` (mm)."""
        ny, nx = self.shape
        return self.x0 + self.spacing * np.arange(nx), self.y0 + self.spacing * np.arange(ny)

    def grid_points(self) -> np.ndarray:
        """``(K, 3)`` world points of the valid cells, row by row."""
        xs, ys = self.coordinates()
        i, j = np.nonzero(self.valid)
        return np.column_stack([xs[j], ys[i], self.z[i, j]])

    def sample_points(self) -> Points | None:
        """The smoothed samples as a :class:`Points` record, or None if not kept.

        Columns, rows and areas missing from the record are filled with -1, NaN and NaN.
        """
        if self.samples is None:
            return None
        m = self.samples.shape[0]

        def pick(value: np.ndarray | None, dtype: str, fill: float) -> np.ndarray:
            if value is None:
                return np.full(m, fill, dtype=dtype)
            return np.ascontiguousarray(value, dtype=dtype)

        return Points(
            x=np.ascontiguousarray(self.samples[:, 0]),
            y=np.ascontiguousarray(self.samples[:, 1]),
            z=np.ascontiguousarray(self.samples[:, 2]),
            number=pick(self.sample_number, "i4", -1),
            col=pick(self.sample_col, "i4", -1),
            row=pick(self.sample_row, "f8", np.nan),
            area=pick(self.sample_area, "f4", np.nan),
            image_shape=np.zeros(2, dtype=np.int64),
            reason=self.reason,
        )

    @classmethod
    def empty(cls, reason: str, *, spacing: float = 1.0) -> Surface:
        """A surface without cells, saying ``reason``."""
        return cls(
            x0=0.0,
            y0=0.0,
            spacing=spacing,
            z=np.zeros((0, 0), dtype=np.float64),
            count=np.zeros((0, 0), dtype=np.int32),
            samples=np.zeros((0, 3), dtype=np.float64),
            sample_number=np.zeros(0, dtype=np.int32),
            sample_col=np.zeros(0, dtype=np.int32),
            sample_row=np.zeros(0, dtype=np.float64),
            sample_area=np.zeros(0, dtype=np.float32),
            reason=reason,
        )


class MeshRecord(Record):
    """A triangle mesh in the world frame, normals facing the camera.

    Attributes
    ----------
    vertices : numpy.ndarray
        ``(N, 3)`` float64 world points (mm).
    triangles : numpy.ndarray
        ``(M, 3)`` int32 vertex indices, wound so that normals point towards the camera
        (``-Z``).
    normals : numpy.ndarray
        ``(N, 3)`` float64 unit vertex normals.
    reason : str
        Why the mesh is empty, or a note.
    """

    kind: ClassVar[str] = "mesh"
    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    reason: str = ""

    def validate(self) -> None:
        """Refuse badly shaped arrays or triangles indexing missing vertices."""
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise InputError(f"MeshRecord.vertices must be (N, 3), got {self.vertices.shape}")
        if self.normals.shape != self.vertices.shape:
            raise InputError(
                f"MeshRecord.normals has shape {self.normals.shape}, vertices {self.vertices.shape}"
            )
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3:
            raise InputError(f"MeshRecord.triangles must be (M, 3), got {self.triangles.shape}")
        if self.triangles.dtype != np.int32:
            raise InputError(f"MeshRecord.triangles must be int32, not {self.triangles.dtype}")
        if self.triangles.size and (
            self.triangles.min() < 0 or self.triangles.max() >= self.vertices.shape[0]
        ):
            raise InputError("MeshRecord.triangles refer to vertices that do not exist")

    @classmethod
    def empty(cls, reason: str) -> MeshRecord:
        """A mesh without vertices, saying ``reason``."""
        return cls(
            vertices=np.zeros((0, 3)),
            triangles=np.zeros((0, 3), dtype=np.int32),
            normals=np.zeros((0, 3)),
            reason=reason,
        )

    def to_open3d(self) -> object:
        """Return an ``open3d.geometry.TriangleMesh`` with the vertex normals."""
        import open3d as o3d

        # open3d wants writeable buffers; record arrays are read-only views, so copy
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(np.array(self.vertices, dtype=np.float64)),
            o3d.utility.Vector3iVector(np.array(self.triangles, dtype=np.int32)),
        )
        mesh.vertex_normals = o3d.utility.Vector3dVector(np.array(self.normals, np.float64))
        return mesh
