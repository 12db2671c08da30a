"""Triangle mesh of a gridded surface: two triangles per fully measured grid cell.

The grid is already organised, so it is triangulated by index, not reconstructed (no Poisson
or ball pivoting, which would invent surface over holes): every cell whose four corners hold
a depth becomes two triangles, split along the shorter 3-D diagonal (the split that follows
a ridge or furrow instead of cutting across it). Vertices of no triangle are dropped.
Triangles are wound so that normals face the camera (``-Z``); vertex normals are open3d's
area-weighted averages of the adjacent triangle normals.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from rasterserver.records_surface import MeshRecord, Surface
from rasterserver.stage import Stage, StageContext, StageParams

__all__ = ["GridMesh", "grid_triangles"]


def grid_triangles(valid: np.ndarray, z: np.ndarray | None = None) -> np.ndarray:
    """Triangles over the cells of a grid whose four corners are valid.

    Parameters
    ----------
    valid : numpy.ndarray
        ``(ny, nx)`` bool.
    z : numpy.ndarray, optional
        ``(ny, nx)`` depths; when given each cell is split along its shorter diagonal in 3-D
        (with equal x and y steps only the depth difference decides), otherwise always along
        the diagonal from its top-right to its bottom-left corner.

    Returns
    -------
    numpy.ndarray
        ``(M, 3)`` int64 flat grid indices ``i * nx + j``, wound clockwise in the image
        (x right, y down), i.e. with normals towards ``-Z``.
    """
    ny, nx = valid.shape
    if ny < 2 or nx < 2:
        return np.zeros((0, 3), dtype=np.int64)
    # normal of (a, b, c) = (b - a) x (c - a); with x right and y down, (v00, v10, v01) has a
    # z component -spacing², i.e. it faces the camera. One compiled loop over the cells
    # (grid_cells); the numba import costs ~0.3 s, hence imported here.
    from .grid_cells import cell_triangles

    depth = np.zeros((1, 1)) if z is None else np.ascontiguousarray(z, dtype=np.float64)
    return cell_triangles(np.ascontiguousarray(valid, dtype=np.bool_), depth, z is not None)


class GridMesh(Stage[Surface, MeshRecord]):
    """Two triangles per fully measured grid cell, with vertex normals (no surface fitting)."""

    name: ClassVar[str] = "mesh.grid"
    stage: ClassVar[str] = "mesh"
    version: ClassVar[str] = "1"
    input_type = Surface
    output_type = MeshRecord

    class Params(StageParams):
        """Parameters of :class:`GridMesh`."""

        shorter_diagonal: bool = Field(
            True, description="Split each cell along its shorter 3-D diagonal (else fixed)."
        )

    def run(self, data: Surface, params: Params, context: StageContext) -> MeshRecord:
        """Triangulate the valid cells of ``data``."""
        valid = data.valid
        triangles = grid_triangles(valid, data.z if params.shorter_diagonal else None)
        if triangles.size == 0:
            why = "no grid cell has four measured corners"
            return MeshRecord.empty(f"{why}; {data.reason}" if data.reason else why)
        from .grid_cells import used_vertices

        ny, nx = data.shape
        flat, tri = used_vertices(triangles, ny * nx)  # vertices of no triangle dropped
        i, j = np.divmod(flat, nx)
        xs, ys = data.coordinates()
        vertices = np.column_stack([xs[j], ys[i], data.z.ravel()[flat]])
        # imported here: open3d costs ~0.6 s, paid by every command that lists the stages
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(tri)
        )
        mesh.compute_vertex_normals()
        return MeshRecord(
            vertices=vertices,
            triangles=tri,
            normals=np.asarray(mesh.vertex_normals, dtype=np.float64),
            reason=data.reason,
        )
