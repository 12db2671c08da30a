"""What the simulator renders: surfaces in the world frame, each with its albedo.

World frame (shared with :mod:`rasterserver.optics`, OpenCV conventions, millimetres): X to the
right as the camera sees it, Y down (towards the floor), Z away from the camera (into the
patient). The origin lies on the nominal back plane on the camera's optical axis; the default
camera sits at ``(0, 0, -2000)`` looking along +Z, the projector 800 mm above it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d

#: Albedo as a function of world points ``(N, 3)`` → reflectance in [0, 1] ``(N,)``.
AlbedoFunction = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class SceneObject:
    """One surface of a scene.

    Attributes
    ----------
    name : str
        What it is (``"trunk"``, ``"left-arm"``, ``"plate-1"``); ground truth labels use it.
    mesh : open3d.geometry.TriangleMesh
        Closed or open triangle mesh in world millimetres, normals facing the camera side.
    albedo : float or AlbedoFunction
        Diffuse reflectance, constant or a function of the world point (skin texture,
        dark control-point holes).
    """

    name: str
    mesh: o3d.geometry.TriangleMesh
    albedo: float | AlbedoFunction = 0.8


@dataclass(frozen=True)
class Scene:
    """Everything in front of the camera, plus what is known exactly about it.

    Attributes
    ----------
    objects : list of SceneObject
        The surfaces.
    landmarks : Mapping[str, numpy.ndarray]
        Named 3-D points or curves (mm), e.g. ``"vertebra_prominens"`` (3,),
        ``"dimple_left"`` (3,), ``"spinal_midline"`` (M, 3).
    metadata : Mapping[str, Any]
        The parameters the scene was made from (JSON-serialisable), e.g. the applied lateral
        deviation and axial rotation of a scoliotic back.
    """

    objects: list[SceneObject]
    landmarks: Mapping[str, np.ndarray] = field(default_factory=dict)
    metadata: Mapping[str, Any] = field(default_factory=dict)
