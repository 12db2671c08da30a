"""Small pieces of rigid-body geometry the comparison shares: the angle of a rotation, a
mesh's area per vertex, a 4x4 transform applied to points."""

from __future__ import annotations

import numpy as np


def rotation_angle(rotation: np.ndarray) -> float:
    """Rotation angle of a 3×3 rotation matrix, degrees."""
    cos = (float(np.trace(rotation)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def vertex_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """A third of the area of every triangle around each vertex (mm²), ``(N,)``."""
    area = np.zeros(len(vertices))
    if len(triangles):
        a, b, c = (vertices[triangles[:, k]] for k in range(3))
        each = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1) / 3.0
        for k in range(3):
            np.add.at(area, triangles[:, k], each)
    return area


def apply_transform(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` (N, 3) moved by the 4×4 rigid ``transform``."""
    return points @ transform[:3, :3].T + transform[:3, 3]
