"""Regions of a distance map where the two visits show differently placed arms, hands or
clothing, not a changed back.

At a clinic the patient comes back with the arms held otherwise (hanging close, away from
the trunk, hands on the hips). The measured surface joins an arm to the trunk wherever it
touches or overlaps it in the image, so the trunk of either visit holds pieces of arm, and
the distance map shows them as a change of 10-30 mm at the flanks of an unchanged back
(``benchmarks/clinic_comparison.py``: 1.8 mm rms on the median unchanged back, 4.9 mm at
worst, against 0.05-0.1 mm inside). Such a region starts at the trunk's outline and
differs by more than a change of the back between two visits, and the difference ramps up
steeply at its edge; a changed back differs by millimetres (a +4° rotation of the moderate
preset's main curve: 12 mm at most), and its difference changes slowly along the surface. The
region, its ramp and a margin around it are marked as not compared, and the map says how
much of the trunk that is.
"""

from __future__ import annotations

import numpy as np

__all__ = ["displaced_regions", "distance_slope", "mesh_boundary"]


def _edges(triangles: np.ndarray) -> np.ndarray:
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    return np.vstack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])


def mesh_boundary(triangles: np.ndarray, count: int) -> np.ndarray:
    """Which of ``count`` vertices lie on the mesh's boundary (an edge of one triangle).

    Parameters
    ----------
    triangles : numpy.ndarray
        ``(M, 3)`` vertex indices.
    count : int
        Number of vertices.

    Returns
    -------
    numpy.ndarray
        ``(count,)`` bool.
    """
    out = np.zeros(count, dtype=bool)
    edges = np.sort(_edges(triangles), axis=1)
    if len(edges) == 0:
        return out
    unique, seen = np.unique(edges, axis=0, return_counts=True)
    out[unique[seen == 1].ravel()] = True
    return out


def distance_slope(vertices: np.ndarray, triangles: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """How steeply the distance changes along the surface at each vertex (mm per mm).

    The gradient of the distance, linear over each triangle, in the triangle's plane; a
    vertex takes the steepest of its triangles'. A triangle with a corner without a value is
    infinitely steep (the distance breaks off there).

    Parameters
    ----------
    vertices : numpy.ndarray
        ``(N, 3)`` vertices (mm).
    triangles : numpy.ndarray
        ``(M, 3)`` vertex indices.
    distance : numpy.ndarray
        ``(N,)`` the distance (mm), NaN without a value.

    Returns
    -------
    numpy.ndarray
        ``(N,)``; 0 for a vertex of no triangle.
    """
    v = np.asarray(vertices, dtype=float)
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    d = np.asarray(distance, dtype=float)
    out = np.zeros(len(v))
    if len(tri) == 0:
        return out
    e1 = v[tri[:, 1]] - v[tri[:, 0]]
    e2 = v[tri[:, 2]] - v[tri[:, 0]]
    a, b, c = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    r1 = d[tri[:, 1]] - d[tri[:, 0]]
    r2 = d[tri[:, 2]] - d[tri[:, 0]]
    with np.errstate(divide="ignore", invalid="ignore"):
        det = a * c - b * b
        # the in-plane gradient g = u e1 + w e2 with g.e1 = r1 and g.e2 = r2
        u = (c * r1 - b * r2) / det
        w = (a * r2 - b * r1) / det
        steep = np.linalg.norm(u[:, None] * e1 + w[:, None] * e2, axis=1)
    steep = np.where(np.isfinite(steep), steep, np.inf)
    for k in range(3):
        np.maximum.at(out, tri[:, k], steep)
    return out


def displaced_regions(
    vertices: np.ndarray,
    triangles: np.ndarray,
    distance: np.ndarray,
    *,
    limit: float,
    slope: float,
    margin: float,
) -> np.ndarray:
    """The vertices of a distance map lying in regions the two visits show otherwise placed.

    A region is a connected piece of the mesh (along its edges) of vertices that differ by
    more than ``limit``, have no counterpart, or where the distance changes more steeply than
    ``slope`` (the ramp from the trunk onto an arm); it must reach the mesh's boundary (the
    trunk's outline, where arms and hands join it) and hold a measured difference beyond
    ``limit``. Its vertices and every vertex within ``margin`` of them are returned. A
    changed back differs inside the trunk, by millimetres, and changes slowly along it.

    Parameters
    ----------
    vertices : numpy.ndarray
        ``(N, 3)`` the map's vertices (mm).
    triangles : numpy.ndarray
        ``(M, 3)`` its triangles.
    distance : numpy.ndarray
        ``(N,)`` signed distance (mm), NaN without a counterpart.
    limit : float
        Difference (mm) beyond any change of the back between two visits.
    slope : float
        Change of the difference along the surface (mm per mm) that joins a region.
    margin : float
        Width (mm) of the band around a region also returned.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True on the displaced regions and their margins.
    """
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    d = np.asarray(distance, dtype=float)
    n = len(d)
    far = np.isfinite(d) & (np.abs(np.nan_to_num(d)) > limit)
    if n == 0 or not far.any():
        return np.zeros(n, dtype=bool)
    joins = far | ~np.isfinite(d) | (distance_slope(vertices, triangles, d) > slope)
    edges = _edges(triangles)
    edges = edges[joins[edges[:, 0]] & joins[edges[:, 1]]]
    graph = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _count, label = connected_components(graph, directed=False)
    outer = joins & mesh_boundary(triangles, n)
    pieces = np.intersect1d(np.unique(label[outer]), np.unique(label[far]))
    region = joins & np.isin(label, pieces)
    if not region.any():
        return region
    near, _ = cKDTree(np.asarray(vertices, dtype=float)[region]).query(
        np.asarray(vertices, dtype=float), distance_upper_bound=margin
    )
    return np.isfinite(near)
