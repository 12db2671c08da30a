"""Ray casting against a :class:`~rasterserver.simulator.scene.Scene` (open3d / Embree).

Embree works in single precision; :meth:`Tracer.exact_points` recomputes hit points in double
precision from the hit triangle's plane, which the ground truth needs (1e-3 px and better).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from rasterserver.simulator.scene import Scene


@dataclass(frozen=True, eq=False)
class Hits:
    """Result of casting ``N`` rays.

    Attributes
    ----------
    t : numpy.ndarray
        ``(N,)`` float32 ray parameter of the hit (inf: nothing hit).
    hit : numpy.ndarray
        ``(N,)`` bool.
    object_index : numpy.ndarray
        ``(N,)`` int16 index into ``scene.objects`` (-1: nothing hit).
    triangle : numpy.ndarray
        ``(N,)`` int64 global triangle index (-1: nothing hit).
    normals : numpy.ndarray
        ``(N, 3)`` float32 unit shading normals facing the ray origin (0 where nothing hit).
    """

    t: np.ndarray
    hit: np.ndarray
    object_index: np.ndarray
    triangle: np.ndarray
    normals: np.ndarray


class Tracer:
    """All meshes of a scene in one Embree scene, plus what is needed to shade the hits.

    Parameters
    ----------
    scene : Scene
        The surfaces to trace.
    smooth_normals : bool
        Interpolate the vertex normals of meshes that have them (smooth shading); meshes
        without vertex normals (boxes, calibration plates) keep their face normals, so
        sharp edges stay sharp.
    """

    def __init__(self, scene: Scene, *, smooth_normals: bool = True) -> None:
        self.scene = scene
        self._rc = o3d.t.geometry.RaycastingScene()
        corners: list[np.ndarray] = []
        corner_normals: list[np.ndarray | None] = []
        offsets = [0]
        geometry_to_object: dict[int, int] = {}
        for index, obj in enumerate(scene.objects):
            vertices = np.asarray(obj.mesh.vertices, dtype=np.float64)
            triangles = np.asarray(obj.mesh.triangles, dtype=np.int64)
            if triangles.size == 0:
                raise ValueError(f"scene object {obj.name!r} has no triangles")
            # open3d's generated stubs drop the defaults (None) of Tensor's dtype and device
            gid = self._rc.add_triangles(
                o3d.core.Tensor(vertices.astype(np.float32)),  # type: ignore[call-overload]
                o3d.core.Tensor(triangles.astype(np.uint32)),  # type: ignore[call-overload]
            )
            geometry_to_object[int(gid)] = index
            corners.append(vertices[triangles])  # (T, 3 corners, 3)
            if smooth_normals and obj.mesh.has_vertex_normals():
                vn = np.asarray(obj.mesh.vertex_normals, dtype=np.float32)
                corner_normals.append(vn[triangles].reshape(-1, 9))
            else:
                corner_normals.append(None)
            offsets.append(offsets[-1] + triangles.shape[0])
        self.object_names: list[str] = [obj.name for obj in scene.objects]
        self.triangle_offsets = np.asarray(offsets, dtype=np.int64)
        self.triangle_corners = (
            np.concatenate(corners) if corners else np.zeros((0, 3, 3), dtype=np.float64)
        )
        self._corner_normals = corner_normals
        max_gid = max(geometry_to_object, default=-1)
        self._gid_to_object = np.full(max_gid + 2, -1, dtype=np.int16)
        for gid, index in geometry_to_object.items():
            self._gid_to_object[gid] = index

    # ------------------------------------------------------------------ casting
    def cast(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """Cast rays ``(N, 3)`` + ``(N, 3)`` (float32 or float64) and shade-prepare the hits."""
        rays = np.concatenate(
            [np.asarray(origins, dtype=np.float32), np.asarray(directions, dtype=np.float32)],
            axis=1,
        )
        return self.cast_rays(rays)

    def cast_rays(self, rays: np.ndarray) -> Hits:
        """Cast a float32 ``(N, 6)`` array ``[origin, direction]``."""
        if rays.shape[0] == 0:
            z = np.zeros(0)
            return Hits(
                z.astype(np.float32),
                z.astype(bool),
                z.astype(np.int16),
                z.astype(np.int64),
                np.zeros((0, 3), np.float32),
            )
        out = self._rc.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
        t = out["t_hit"].numpy()
        hit = np.isfinite(t)
        everything = bool(hit.all())
        prim = out["primitive_ids"].numpy()
        if len(self.object_names) == 1:
            # one mesh (the common case): no id mapping needed
            obj = np.zeros(t.size, dtype=np.int16)
            tri = prim.astype(np.int64)
        else:
            gid = np.minimum(out["geometry_ids"].numpy(), self._gid_to_object.size - 1)
            obj = self._gid_to_object[gid]  # INVALID_ID (uint max) → the trailing -1 slot
            tri = self.triangle_offsets[np.maximum(obj, 0)] + prim
        if not everything:
            obj[~hit] = -1
            tri[~hit] = -1
        normals = out["primitive_normals"].numpy()
        normals = self._smooth(normals, out["primitive_uvs"].numpy(), obj, tri, hit)
        # face the viewer: meshes may be oriented either way
        flip = np.einsum("ij,ij->i", normals, rays[:, 3:6]) > 0
        normals[flip] *= -1.0
        if not everything:
            normals[~hit] = 0.0
        return Hits(t=t, hit=hit, object_index=obj, triangle=tri, normals=normals)

    def _smooth(
        self,
        normals: np.ndarray,
        uvs: np.ndarray,
        obj: np.ndarray,
        tri: np.ndarray,
        hit: np.ndarray,
    ) -> np.ndarray:
        for index, cn in enumerate(self._corner_normals):
            if cn is None:
                continue
            sel = np.flatnonzero(hit & (obj == index))
            if sel.size == 0:
                continue
            everything = sel.size == obj.size
            local = (tri if everything else tri[sel]) - self.triangle_offsets[index]
            c = np.take(cn, local, axis=0).reshape(-1, 3, 3)
            weights = np.empty((sel.size, 3), dtype=np.float32)  # barycentric
            weights[:, 1:] = uvs if everything else uvs[sel]
            weights[:, 0] = 1.0 - weights[:, 1] - weights[:, 2]
            n = np.einsum("nj,njk->nk", weights, c)
            n *= (1.0 / np.sqrt(np.maximum(np.einsum("ij,ij->i", n, n), 1e-24)))[:, None]
            if everything:
                normals = n
            else:
                normals[sel] = n
        return normals

    def occluded(
        self, points: np.ndarray, normals: np.ndarray, target: np.ndarray, *, epsilon: float = 0.05
    ) -> np.ndarray:
        """Whether the segments from surface points to ``target`` (the projector) are blocked.

        Parameters
        ----------
        points, normals : numpy.ndarray
            ``(N, 3)`` surface points and their normals (on the side facing ``target``).
        target : numpy.ndarray
            ``(3,)`` end point of every segment.
        epsilon : float
            Offset (mm) along the normal so that a point does not shadow itself.

        Returns
        -------
        numpy.ndarray
            ``(N,)`` bool.
        """
        if points.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        rays = np.empty((points.shape[0], 6), dtype=np.float32)
        start = points + np.float32(epsilon) * normals
        rays[:, :3] = start
        np.subtract(target.astype(np.float32)[None, :], start, out=rays[:, 3:])
        occ = self._rc.test_occlusions(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)), tnear=0.0, tfar=1.0
        )
        return occ.numpy().astype(bool)

    def exact_points(
        self, origins: np.ndarray, directions: np.ndarray, triangle: np.ndarray
    ) -> np.ndarray:
        """Double-precision intersection of rays with the planes of their hit triangles.

        Parameters
        ----------
        origins, directions : numpy.ndarray
            ``(N, 3)`` float64 rays.
        triangle : numpy.ndarray
            ``(N,)`` global triangle index from :meth:`cast` (-1: NaN result).

        Returns
        -------
        numpy.ndarray
            ``(N, 3)`` float64 points.
        """
        out = np.full(origins.shape, np.nan)
        ok = triangle >= 0
        if not np.any(ok):
            return out
        c = self.triangle_corners[triangle[ok]]
        n = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
        o, d = origins[ok], directions[ok]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.einsum("ij,ij->i", n, c[:, 0] - o) / np.einsum("ij,ij->i", n, d)
        out[ok] = o + s[:, None] * d
        return out
