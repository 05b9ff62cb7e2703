"""Ray-cast rendering of a triangle mesh into depth and colour images of pinhole cameras.

The ray of pixel (u, v) leaves the camera centre through ((u - cx) / fx, (v - cy) / fy, 1) in
the camera frame (OpenCV: x right, y down, z forward, pixel centres at integer coordinates).
Because that direction has unit z, the hit distance open3d returns is the z-depth itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import Intrinsics
from pipeline.geometry.mesh import TriangleMesh, vertex_normals

_AMBIENT = 0.3
# Fixed world lights (direction towards the light, weight): colour then does not depend on
# the viewing camera, as for a diffuse subject under studio lights.
_LIGHTS = (((0.35, 1.0, 0.55), 0.55), ((-0.6, 0.25, -0.75), 0.3))
_CHECKER_CELL_M = 0.12


@dataclass(frozen=True)
class Rendering:
    """What one camera sees of the mesh; misses are 0 / -1 / zero vectors."""

    depth_m: NDArray[np.float32]
    """(H, W) metres along the camera's z axis; 0 where the ray misses the mesh."""
    triangle_ids: NDArray[np.int64]
    """(H, W) index of the hit triangle; -1 where the ray misses."""
    normals_cam: NDArray[np.float32]
    """(H, W, 3) unit geometric (face) normals in the camera frame, turned towards the camera."""
    shading_normals_world: NDArray[np.float32]
    """(H, W, 3) unit interpolated vertex normals in the world, turned towards the camera."""
    points_world: NDArray[np.float32]
    """(H, W, 3) hit points in the world, metres (zero where missed)."""

    @property
    def hit(self) -> NDArray[np.bool_]:
        """(H, W) True where the ray hit the mesh."""
        return self.triangle_ids >= 0


class MeshRaycaster:
    """A mesh prepared once for casting rays from many cameras."""

    def __init__(self, mesh: TriangleMesh) -> None:
        import open3d as o3d

        if mesh.face_count == 0:
            raise ValueError("mesh: has no triangles to render")
        self.mesh = mesh
        self._vertex_normals = (mesh.vertex_normals if mesh.vertex_normals is not None
                                else vertex_normals(mesh.vertices_m, mesh.faces))
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(mesh.vertices_m, dtype=np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(mesh.faces, dtype=np.uint32)))

    def render(self, intrinsics: Intrinsics,
               world_from_depth: NDArray[np.float64]) -> Rendering:
        """Casts one ray per pixel from the camera at `world_from_depth` (4x4, metres)."""
        import open3d as o3d

        if intrinsics.has_distortion:
            raise ValueError("intrinsics: the synthetic renderer models no lens distortion")
        pose = np.asarray(world_from_depth, dtype=np.float64)
        if pose.shape != (4, 4):
            raise ValueError(f"world_from_depth: expected 4x4, got {pose.shape}")
        dirs_cam = pixel_rays(intrinsics)
        dirs_world = dirs_cam @ pose[:3, :3].T
        rays = np.empty((intrinsics.height, intrinsics.width, 6), dtype=np.float32)
        rays[..., :3] = pose[:3, 3]
        rays[..., 3:] = dirs_world
        result = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t_hit = result["t_hit"].numpy()
        hit = np.isfinite(t_hit)
        ids = np.where(hit, result["primitive_ids"].numpy().astype(np.int64), -1)
        depth = np.where(hit, t_hit, 0.0).astype(np.float32)
        face_n = result["primitive_normals"].numpy().astype(np.float64)
        # Two-sided: a surface seen from behind (open meshes, bad winding) still reflects.
        facing = np.where(np.sum(face_n * dirs_world, axis=-1, keepdims=True) > 0, -1.0, 1.0)
        normals_cam = ((face_n * facing) @ pose[:3, :3]) * hit[..., None]
        smooth = self._smooth_normals(ids, result["primitive_uvs"].numpy(), hit)
        smooth_facing = np.where(np.sum(smooth * dirs_world, axis=-1, keepdims=True) > 0, -1, 1)
        points = (pose[:3, 3] + dirs_world * depth[..., None]) * hit[..., None]
        return Rendering(depth_m=depth, triangle_ids=ids,
                         normals_cam=normals_cam.astype(np.float32),
                         shading_normals_world=(smooth * smooth_facing).astype(np.float32),
                         points_world=points.astype(np.float32))

    def _smooth_normals(self, ids: NDArray[np.int64], uvs: NDArray[np.float32],
                        hit: NDArray[np.bool_]) -> NDArray[np.float64]:
        normals = np.zeros(ids.shape + (3,))
        corners = self.mesh.faces[ids[hit]]
        u, v = uvs[hit, 0:1].astype(np.float64), uvs[hit, 1:2].astype(np.float64)
        vn = self._vertex_normals.astype(np.float64)
        blended = (1 - u - v) * vn[corners[:, 0]] + u * vn[corners[:, 1]] + v * vn[corners[:, 2]]
        length = np.linalg.norm(blended, axis=1, keepdims=True)
        normals[hit] = np.divide(blended, length, out=np.zeros_like(blended), where=length > 0)
        return normals


def pixel_rays(intrinsics: Intrinsics) -> NDArray[np.float64]:
    """(H, W, 3) ray directions in the camera frame with unit z, one per pixel centre."""
    u = (np.arange(intrinsics.width) - intrinsics.cx) / intrinsics.fx
    v = (np.arange(intrinsics.height) - intrinsics.cy) / intrinsics.fy
    dirs = np.ones((intrinsics.height, intrinsics.width, 3))
    dirs[..., 0] = u[None, :]
    dirs[..., 1] = v[:, None]
    return dirs


def render_depth(mesh: TriangleMesh | MeshRaycaster, intrinsics: Intrinsics,
                 world_from_depth: NDArray[np.float64]) -> Rendering:
    """Renders one camera; pass a `MeshRaycaster` to render many cameras of one mesh cheaply."""
    caster = mesh if isinstance(mesh, MeshRaycaster) else MeshRaycaster(mesh)
    return caster.render(intrinsics, world_from_depth)


def procedural_albedo(points_world: NDArray[np.floating]) -> NDArray[np.float64]:
    """(..., 3) diffuse albedo in [0, 1] of world points (metres).

    Meshes carry no colour, so the subject is painted with a smooth colour field of its
    position (hue drifting with height and azimuth) times a 3D checker of 12 cm cells, which
    gives the colour images sharp edges to detect.
    """
    p = np.asarray(points_world, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    azimuth = np.arctan2(x, z)
    base = np.stack([0.55 + 0.3 * np.sin(2.2 * y + 0.4),
                     0.5 + 0.3 * np.sin(1.7 * y + azimuth + 2.0),
                     0.5 + 0.3 * np.cos(2.9 * y - azimuth)], axis=-1)
    cells = np.floor(p / _CHECKER_CELL_M).astype(np.int64).sum(axis=-1)
    checker = np.where(cells % 2 == 0, 1.0, 0.55)
    return np.clip(base * checker[..., None], 0.0, 1.0)


def lambert_shading(normals_world: NDArray[np.floating]) -> NDArray[np.float64]:
    """(...) light reaching a diffuse surface with these unit normals under the fixed lights."""
    light = np.full(normals_world.shape[:-1], _AMBIENT)
    for direction, weight in _LIGHTS:
        d = np.asarray(direction) / np.linalg.norm(direction)
        light += weight * np.clip(normals_world @ d, 0.0, None)
    return light


def shade_color(rendering: Rendering) -> NDArray[np.uint8]:
    """(H, W, 3) sRGB colour image registered to the depth image; black where missed."""
    albedo = procedural_albedo(rendering.points_world)
    radiance = albedo * lambert_shading(rendering.shading_normals_world)[..., None]
    radiance *= rendering.hit[..., None]
    return np.clip(np.rint(radiance * 255.0), 0, 255).astype(np.uint8)


def albedo_colors(points_world: NDArray[np.floating]) -> NDArray[np.uint8]:
    """(N, 3) sRGB albedo of points (for the ground-truth mesh's vertex colours)."""
    return np.clip(np.rint(procedural_albedo(points_world) * 255.0), 0, 255).astype(np.uint8)
