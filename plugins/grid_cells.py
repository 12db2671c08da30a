"""The mesh's triangles over the grid's measured cells, compiled with numba.

:func:`rasterserver_plugins.mesh.grid_triangles` built them with whole-array passes (cell
masks, four corner gathers for the diagonals, two stacked candidates per triangle and a
``where`` between them): ~2 of the mesh stage's ~5 ms. One loop over the cells writes each
triangle once, in the same order (cells row by row; all first triangles, then all second
ones), so the mesh is the same and the plugin's version does not change.

Importing this module costs the numba import (~0.3 s): the mesh stage imports it on use.
"""

from __future__ import annotations

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def cell_triangles(valid: np.ndarray, z: np.ndarray, shorter_diagonal: bool) -> np.ndarray:
    """Two triangles per cell of ``valid`` whose four corners are valid.

    Parameters
    ----------
    valid : numpy.ndarray
        ``(ny, nx)`` bool, ``ny, nx >= 2``.
    z : numpy.ndarray
        ``(ny, nx)`` float64 depths (read only when ``shorter_diagonal``).
    shorter_diagonal : bool
        Split along the shorter 3-D diagonal; else from top-right to bottom-left.

    Returns
    -------
    numpy.ndarray
        ``(2 M, 3)`` int64 flat grid indices, the cells' first triangles then their second.
    """
    ny, nx = valid.shape
    m = 0
    for i in range(ny - 1):
        for j in range(nx - 1):
            if valid[i, j] and valid[i, j + 1] and valid[i + 1, j] and valid[i + 1, j + 1]:
                m += 1
    out = np.empty((2 * m, 3), dtype=np.int64)
    k = 0
    for i in range(ny - 1):
        for j in range(nx - 1):
            if not (valid[i, j] and valid[i, j + 1] and valid[i + 1, j] and valid[i + 1, j + 1]):
                continue
            v00 = i * nx + j
            v01 = v00 + 1
            v10 = v00 + nx
            v11 = v10 + 1
            main = shorter_diagonal and (
                abs(z[i, j] - z[i + 1, j + 1]) < abs(z[i, j + 1] - z[i + 1, j])
            )
            if main:
                out[k, 0], out[k, 1], out[k, 2] = v00, v10, v11
                out[m + k, 0], out[m + k, 1], out[m + k, 2] = v00, v11, v01
            else:
                out[k, 0], out[k, 1], out[k, 2] = v00, v10, v01
                out[m + k, 0], out[m + k, 1], out[m + k, 2] = v01, v10, v11
            k += 1
    return out


@kernel()
def used_vertices(triangles: np.ndarray, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """The grid nodes that triangles use, and the triangles renumbered over them.

    Parameters
    ----------
    triangles : numpy.ndarray
        ``(M, 3)`` int64 flat grid indices.
    n_nodes : int
        Number of grid nodes.

    Returns
    -------
    flat : numpy.ndarray
        int64 flat indices of the used nodes, ascending (the mesh's vertices in order).
    renumbered : numpy.ndarray
        ``(M, 3)`` int32 vertex indices into ``flat``.
    """
    new_index = np.full(n_nodes, -1, dtype=np.int64)
    for t in range(triangles.shape[0]):
        for c in range(3):
            new_index[triangles[t, c]] = 0
    count = 0
    for v in range(n_nodes):
        if new_index[v] == 0:
            new_index[v] = count
            count += 1
    flat = np.empty(count, dtype=np.int64)
    for v in range(n_nodes):
        if new_index[v] >= 0:
            flat[new_index[v]] = v
    renumbered = np.empty(triangles.shape, dtype=np.int32)
    for t in range(triangles.shape[0]):
        for c in range(3):
            renumbered[t, c] = new_index[triangles[t, c]]
    return flat, renumbered
