"""Vertex colours from the cameras' colour images.

Every vertex is projected into every colour image; a view counts for a vertex when the vertex
faces it and, where the view has a depth image, when that depth image sees the vertex itself
rather than something in front of it. The colours of the views that count are sampled
bilinearly and averaged, weighted by cos(angle between the normal and the view ray) over the
distance to the camera. Vertices no view sees take the colour of the nearest vertex that was
seen.

Colour need not be registered to depth: a :class:`ColorView` holds the colour camera's model and
pose for sampling and, separately, the depth camera's model and pose for the visibility test.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from pipeline.capture import Intrinsics, View
from pipeline.geometry.mesh import TriangleMesh, vertex_normals

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ColorView:
    """One colour image, where it was taken from, and optionally a depth image to test
    visibility with."""

    image_rgb: NDArray[np.uint8]
    """(H, W, 3) RGB, sRGB."""
    intrinsics: Intrinsics
    """The colour camera's model; its width and height are the image's."""
    world_from_camera: FloatArray
    """(4, 4) pose of the colour camera in the world, metres (OpenCV camera axes)."""
    depth_m: NDArray[np.float32] | None = None
    """(Hd, Wd) metres along the depth camera's z; 0 where there is no measurement. None: no
    occlusion test (every vertex in front of the camera and facing it counts as seen)."""
    depth_intrinsics: Intrinsics | None = None
    """The depth camera's model; None when ``depth_m`` is registered to the colour image."""
    world_from_depth: FloatArray | None = None
    """(4, 4) pose of the depth camera; None when ``depth_m`` is registered to the colour image."""

    def __post_init__(self) -> None:
        _check_image(self.image_rgb, self.intrinsics)
        _check_pose(self.world_from_camera, "world_from_camera")
        if (self.depth_intrinsics is None) != (self.world_from_depth is None):
            raise ValueError("ColorView: depth_intrinsics and world_from_depth go together "
                             "(both None means depth registered to colour)")
        if self.world_from_depth is not None:
            _check_pose(self.world_from_depth, "world_from_depth")
        if self.depth_m is not None:
            model = self.depth_intrinsics or self.intrinsics
            if np.shape(self.depth_m) != (model.height, model.width):
                raise ValueError(f"ColorView.depth_m: shape {np.shape(self.depth_m)} does not "
                                 f"match its camera model ({model.height}, {model.width})")

    @classmethod
    def from_view(cls, view: View) -> ColorView:
        """A colour view from a capture view with a known pose and a colour image.

        Unregistered colour is placed at ``world_from_depth @ inv(color_from_depth)`` and the
        depth image keeps its own camera for the visibility test.
        """
        camera = view.camera
        if view.color_rgb is None:
            raise ValueError(f"camera {camera.id!r} frame {view.frame_index}: no colour image")
        if camera.world_from_depth is None:
            raise ValueError(f"camera {camera.id!r}: world_from_depth unknown (calibrate first)")
        world_from_depth = np.asarray(camera.world_from_depth, dtype=np.float64)
        if camera.color_intrinsics is None:
            return cls(view.color_rgb, camera.depth_intrinsics, world_from_depth, view.depth_m)
        if camera.color_from_depth is None:
            raise ValueError(f"camera {camera.id!r}: color_intrinsics without color_from_depth")
        world_from_color = world_from_depth @ np.linalg.inv(camera.color_from_depth)
        return cls(view.color_rgb, camera.color_intrinsics, world_from_color, view.depth_m,
                   camera.depth_intrinsics, world_from_depth)


@dataclass(frozen=True)
class ColorizeConfig:
    """How views are judged and weighted."""

    depth_tolerance_m: float = 0.02
    """A view's depth image sees a vertex when its measured depth at the vertex's pixel is
    within this of the vertex's own depth, metres (covers sensor noise and mesh smoothing)."""
    min_cos: float = 0.1
    """Views seeing the surface more obliquely than this (cosine of the angle between the
    normal and the ray to the camera) are ignored: their colour is smeared."""
    reject_depth_edges: bool = True
    """Also drop a sample unless all four depth pixels around the vertex's projection measured
    its surface: next to a silhouette or an occluder's edge, the bilinear colour sample would
    blend in the background or the occluder."""
    fallback_rgb: tuple[int, int, int] = (128, 128, 128)
    """Colour for every vertex when no view sees any vertex at all."""

    def __post_init__(self) -> None:
        if not self.depth_tolerance_m > 0:
            raise ValueError(f"ColorizeConfig.depth_tolerance_m must be > 0, "
                             f"got {self.depth_tolerance_m}")
        if not 0 <= self.min_cos < 1:
            raise ValueError(f"ColorizeConfig.min_cos must be in [0, 1), got {self.min_cos}")
        if len(self.fallback_rgb) != 3 or not all(0 <= c <= 255 for c in self.fallback_rgb):
            raise ValueError(f"ColorizeConfig.fallback_rgb must be 3 values in [0, 255], "
                             f"got {self.fallback_rgb}")


def colorize(
    vertices_m: FloatArray,
    normals: NDArray[np.floating],
    views: Sequence[ColorView],
    config: ColorizeConfig = ColorizeConfig(),  # noqa: B008 - frozen, so sharing is safe
    progress: Callable[[float], None] | None = None,
) -> NDArray[np.uint8]:
    """(V, 3) uint8 colours for (V, 3) world vertices (metres) with (V, 3) outward normals."""
    vertices = np.asarray(vertices_m, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
        raise ValueError(f"vertices_m must be finite with shape (V, 3), got {vertices.shape}")
    unit_normals = np.asarray(normals, dtype=np.float64)
    if unit_normals.shape != vertices.shape:
        raise ValueError(f"normals must have shape {vertices.shape}, got {unit_normals.shape}")
    if len(views) == 0:
        raise ValueError("views: need at least one colour view")
    length = np.linalg.norm(unit_normals, axis=1, keepdims=True)
    unit_normals = np.divide(unit_normals, length, out=np.zeros_like(unit_normals),
                             where=length > 0)
    weight_sum = np.zeros(len(vertices))
    color_sum = np.zeros((len(vertices), 3))
    for done, view in enumerate(views):
        index, weights, colors = _view_contribution(vertices, unit_normals, view, config)
        weight_sum[index] += weights
        color_sum[index] += weights[:, None] * colors
        if progress is not None:
            progress((done + 1) / len(views))
    seen = weight_sum > 0
    result = np.empty((len(vertices), 3), dtype=np.uint8)
    result[seen] = np.clip(np.rint(color_sum[seen] / weight_sum[seen, None]), 0, 255)
    if not seen.any():
        result[:] = config.fallback_rgb
    elif not seen.all():
        _, nearest = cKDTree(vertices[seen]).query(vertices[~seen])
        result[~seen] = result[seen][nearest]
    return result


def colorize_mesh(
    mesh: TriangleMesh,
    views: Sequence[ColorView],
    config: ColorizeConfig = ColorizeConfig(),  # noqa: B008
    progress: Callable[[float], None] | None = None,
) -> TriangleMesh:
    """The mesh with vertex colours from ``views`` (normals computed when it has none)."""
    normals = mesh.vertex_normals
    if normals is None:
        normals = vertex_normals(mesh.vertices_m, mesh.faces)
    colors = colorize(mesh.vertices_m, normals, views, config, progress)
    return TriangleMesh(mesh.vertices_m, mesh.faces, colors, mesh.vertex_normals)


def _view_contribution(
    vertices: FloatArray, normals: FloatArray, view: ColorView, config: ColorizeConfig
) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
    """Indices of the vertices this view colours, their weights and (n, 3) sampled colours."""
    centre = view.world_from_camera[:3, 3]
    to_camera = centre - vertices
    distance = np.linalg.norm(to_camera, axis=1)
    cosine = np.einsum("ij,ij->i", normals, to_camera) / np.maximum(distance, 1e-12)
    candidates = np.flatnonzero(cosine > config.min_cos)
    pixels, inside = _project(vertices[candidates], view.intrinsics, view.world_from_camera)
    candidates, pixels = candidates[inside], pixels[inside]
    if view.depth_m is not None:
        visible = _depth_agrees(vertices[candidates], normals[candidates], view, config)
        candidates, pixels = candidates[visible], pixels[visible]
    weights = cosine[candidates] / np.maximum(distance[candidates], 1e-12)
    return candidates, weights, _sample_bilinear(view.image_rgb, pixels)


def _depth_agrees(
    points_world: FloatArray, normals: FloatArray, view: ColorView, config: ColorizeConfig
) -> NDArray[np.bool_]:
    """Whether the view's depth image measured each point itself (not an occluder)."""
    assert view.depth_m is not None
    # Registered depth shares the colour camera's model and pose.
    model = view.depth_intrinsics or view.intrinsics
    world_from_depth = view.world_from_camera
    if view.world_from_depth is not None:
        world_from_depth = view.world_from_depth
    pixels, inside = _project(points_world, model, world_from_depth)
    depth_from_world = np.linalg.inv(world_from_depth)
    own_depth = points_world[inside] @ depth_from_world[2, :3] + depth_from_world[2, 3]
    # A pixel d pixels away sees the surface about d * (z / f) * tan(angle) deeper or
    # shallower: on oblique surfaces that exceeds any fixed tolerance within one pixel.
    to_camera = world_from_depth[:3, 3] - points_world[inside]
    cosine = np.einsum("ij,ij->i", normals[inside], to_camera) / np.maximum(
        np.linalg.norm(to_camera, axis=1), 1e-12)
    cosine = np.clip(cosine, max(config.min_cos, 1e-3), 1.0)
    slope_m_per_px = own_depth / (0.5 * (model.fx + model.fy)) * np.sqrt(1 - cosine**2) / cosine
    uv = pixels[inside]
    if config.reject_depth_edges:
        x0 = np.clip(np.floor(uv[:, 0]).astype(np.intp), 0, model.width - 2)
        y0 = np.clip(np.floor(uv[:, 1]).astype(np.intp), 0, model.height - 2)
        corners = [(y0, x0), (y0, x0 + 1), (y0 + 1, x0), (y0 + 1, x0 + 1)]
    else:
        corners = [(np.rint(uv[:, 1]).astype(np.intp), np.rint(uv[:, 0]).astype(np.intp))]
    depth = np.asarray(view.depth_m)
    surface = np.ones(len(own_depth), dtype=bool)
    # Measured depths are compared pixel by pixel, never interpolated: interpolating across a
    # depth edge invents surfaces.
    for rows, cols in corners:
        measured = depth[rows, cols].astype(np.float64)
        offset_px = np.hypot(cols - uv[:, 0], rows - uv[:, 1])
        allowed = config.depth_tolerance_m + offset_px * slope_m_per_px
        surface &= (measured > 0) & (np.abs(measured - own_depth) <= allowed)
    agrees = np.zeros(len(points_world), dtype=bool)
    agrees[inside] = surface
    return agrees


def _project(
    points_world: FloatArray, model: Intrinsics, world_from_camera: FloatArray
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """(N, 2) pixel coordinates (OpenCV: pixel centres at integers) and which land inside."""
    camera_from_world = np.linalg.inv(world_from_camera)
    points_cam = points_world @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
    z = points_cam[:, 2]
    front = z > 1e-6
    normalized = np.zeros((len(points_cam), 2))
    normalized[front] = points_cam[front, :2] / z[front, None]
    pixels = np.full((len(points_cam), 2), -1.0)
    if model.has_distortion:
        # Lens polynomials fold far-off-axis points back into the image: keep only directions
        # inside the image's own field of view before distorting.
        low, high = _field_of_view(model)
        front &= np.all((normalized >= low) & (normalized <= high), axis=1)
        if front.any():
            projected, _ = cv2.projectPoints(points_cam[front].reshape(-1, 1, 3), np.zeros(3),
                                             np.zeros(3), model.matrix(),
                                             model.distortion_coeffs())
            pixels[front] = projected.reshape(-1, 2)
    else:
        pixels[front] = normalized[front] * [model.fx, model.fy] + [model.cx, model.cy]
    inside = front & (pixels[:, 0] >= 0) & (pixels[:, 0] <= model.width - 1) \
        & (pixels[:, 1] >= 0) & (pixels[:, 1] <= model.height - 1)
    return pixels, inside


def _field_of_view(model: Intrinsics) -> tuple[FloatArray, FloatArray]:
    """Normalised-coordinate box (low, high) holding the undistorted image border, 5% wider."""
    steps = np.linspace(0.0, 1.0, 17)
    w, h = model.width - 1, model.height - 1
    border = np.concatenate([
        np.column_stack([steps * w, np.zeros_like(steps)]),
        np.column_stack([steps * w, np.full_like(steps, h)]),
        np.column_stack([np.zeros_like(steps), steps * h]),
        np.column_stack([np.full_like(steps, w), steps * h]),
    ])
    undistorted = cv2.undistortPoints(border.reshape(-1, 1, 2), model.matrix(),
                                      model.distortion_coeffs()).reshape(-1, 2)
    low, high = undistorted.min(axis=0), undistorted.max(axis=0)
    margin = 0.05 * (high - low)
    return low - margin, high + margin


def _sample_bilinear(image: NDArray[np.uint8], pixels: FloatArray) -> FloatArray:
    """(N, 3) colours at (N, 2) pixel positions inside the image, bilinearly interpolated."""
    height, width = image.shape[:2]
    x0 = np.clip(np.floor(pixels[:, 0]).astype(np.intp), 0, width - 2)
    y0 = np.clip(np.floor(pixels[:, 1]).astype(np.intp), 0, height - 2)
    fx = (pixels[:, 0] - x0)[:, None]
    fy = (pixels[:, 1] - y0)[:, None]

    def at(rows: NDArray[np.intp], cols: NDArray[np.intp]) -> FloatArray:
        return image[rows, cols].astype(np.float64)

    top = at(y0, x0) * (1 - fx) + at(y0, x0 + 1) * fx
    bottom = at(y0 + 1, x0) * (1 - fx) + at(y0 + 1, x0 + 1) * fx
    return np.asarray(top * (1 - fy) + bottom * fy)


def _check_image(image: NDArray[np.uint8], model: Intrinsics) -> None:
    shape = np.shape(image)
    if len(shape) != 3 or shape[2] != 3 or np.asarray(image).dtype != np.uint8:
        raise ValueError(f"ColorView.image_rgb must be (H, W, 3) uint8, got {shape} "
                         f"{np.asarray(image).dtype}")
    if shape[:2] != (model.height, model.width):
        raise ValueError(f"ColorView.image_rgb: shape {shape[:2]} does not match intrinsics "
                         f"({model.height}, {model.width})")
    if model.width < 2 or model.height < 2:
        raise ValueError("ColorView.intrinsics: image must be at least 2x2 pixels")


def _check_pose(pose: FloatArray, name: str) -> None:
    if np.shape(pose) != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"ColorView.{name} must be a finite 4x4 matrix, got shape "
                         f"{np.shape(pose)}")
