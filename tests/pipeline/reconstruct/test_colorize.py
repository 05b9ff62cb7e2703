"""Vertex colours from colour images of analytically ray-cast spheres and rectangles."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.capture import CameraInfo, Intrinsics, View
from pipeline.geometry.mesh import TriangleMesh
from pipeline.reconstruct.colorize import ColorizeConfig, ColorView, colorize, colorize_mesh

ColorFn = Callable[[np.ndarray], np.ndarray]  # (N, 3) world points -> (N, 3) RGB floats
RED = np.array([230.0, 20.0, 20.0])


@dataclass(frozen=True)
class Sphere:
    centre: np.ndarray
    radius: float
    color: ColorFn

    def hit(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Ray parameter of the first hit (inf for a miss); rays are origin + t * dirs."""
        offset = origin - self.centre
        a = np.einsum("ij,ij->i", dirs, dirs)
        b = 2.0 * dirs @ offset
        c = offset @ offset - self.radius**2
        disc = b * b - 4 * a * c
        t = np.full(len(dirs), np.inf)
        ok = disc >= 0
        t[ok] = (-b[ok] - np.sqrt(disc[ok])) / (2 * a[ok])
        t[t <= 0] = np.inf
        return t


@dataclass(frozen=True)
class Rect:
    centre: np.ndarray
    half_u: np.ndarray
    half_v: np.ndarray
    color: ColorFn

    def hit(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        normal = np.cross(self.half_u, self.half_v)
        denom = dirs @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.centre - origin) @ normal) / denom
        t = np.where(np.isfinite(t) & (t > 0), t, np.inf)
        points = origin + np.where(np.isfinite(t), t, 0)[:, None] * dirs - self.centre
        s = points @ self.half_u / (self.half_u @ self.half_u)
        r = points @ self.half_v / (self.half_v @ self.half_v)
        return np.where((np.abs(s) <= 1) & (np.abs(r) <= 1), t, np.inf)


def look_at(eye: Sequence[float] | np.ndarray, target: Sequence[float] | np.ndarray) -> np.ndarray:
    """world_from_camera for an OpenCV camera at `eye` looking at `target`, world +Y up."""
    eye_a, target_a = np.asarray(eye, float), np.asarray(target, float)
    z = target_a - eye_a
    z /= np.linalg.norm(z)
    up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.99 else np.array([0.0, 0.0, 1.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = eye_a
    return pose


def intrinsics(width: int = 160, height: int = 120, f: float = 150.0,
               distortion: tuple[float, ...] = ()) -> Intrinsics:
    return Intrinsics(width, height, f, f * 1.01, (width - 1) / 2 + 1.3, (height - 1) / 2 - 0.7,
                      distortion)


def render(shapes: Sequence[Sphere | Rect], model: Intrinsics,
           world_from_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(depth_m float32, 0 = miss; rgb uint8, black background) seen by this camera."""
    xs, ys = np.meshgrid(np.arange(model.width, dtype=float), np.arange(model.height, dtype=float))
    pixels = np.column_stack([xs.ravel(), ys.ravel()])
    if model.has_distortion:
        normalized = cv2.undistortPoints(pixels.reshape(-1, 1, 2), model.matrix(),
                                         model.distortion_coeffs(),
                                         criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                                   100, 1e-12)).reshape(-1, 2)
    else:
        normalized = (pixels - [model.cx, model.cy]) / [model.fx, model.fy]
    dirs_cam = np.column_stack([normalized, np.ones(len(normalized))])  # z = 1: t is depth
    dirs = dirs_cam @ world_from_camera[:3, :3].T
    origin = world_from_camera[:3, 3]
    hits = np.stack([shape.hit(origin, dirs) for shape in shapes])
    nearest = np.argmin(hits, axis=0)
    t = hits[nearest, np.arange(len(dirs))]
    rgb = np.zeros((len(dirs), 3))
    for index, shape in enumerate(shapes):
        mine = (nearest == index) & np.isfinite(t)
        rgb[mine] = shape.color(origin + t[mine, None] * dirs[mine])
    depth = np.where(np.isfinite(t), t, 0.0).astype(np.float32)
    size = (model.height, model.width)
    return depth.reshape(size), np.clip(np.rint(rgb), 0, 255).astype(np.uint8).reshape(*size, 3)


def registered_view(shapes: Sequence[Sphere | Rect], model: Intrinsics, pose: np.ndarray,
                    with_depth: bool = True) -> ColorView:
    depth, rgb = render(shapes, model, pose)
    return ColorView(rgb, model, pose, depth if with_depth else None)


CENTRE = np.array([0.1, 1.0, -0.2])
RADIUS = 0.3


def sphere_color(points: np.ndarray) -> np.ndarray:
    return 127.5 + 120.0 * (points - CENTRE) / RADIUS


def sphere_mesh(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    unit = np.asarray(trimesh.creation.icosphere(subdivisions=subdivisions).vertices)
    return CENTRE + RADIUS * unit, unit


def plane_grid(z: float = 0.0, half: float = 0.5, n: int = 41) -> tuple[np.ndarray, np.ndarray]:
    u = np.linspace(-half, half, n)
    xs, ys = np.meshgrid(u, u + 1.0)
    vertices = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)])
    return vertices, np.tile([0.0, 0.0, 1.0], (len(vertices), 1))


def plane_color(points: np.ndarray) -> np.ndarray:
    return np.column_stack([40 + 150 * (points[:, 0] + 0.6), 180 + 0 * points[:, 0],
                            60 + 100 * (points[:, 1] - 0.4)])


def well_seen(vertices: np.ndarray, normals: np.ndarray, poses: Sequence[np.ndarray],
              min_cos: float = 0.3) -> np.ndarray:
    best = np.zeros(len(vertices))
    for pose in poses:
        ray = pose[:3, 3] - vertices
        best = np.maximum(best, np.sum(normals * ray, axis=1) / np.linalg.norm(ray, axis=1))
    return best > min_cos


# --- recovery --------------------------------------------------------------------------------


def test_two_cameras_recover_the_colours_of_a_sphere() -> None:
    vertices, normals = sphere_mesh()
    scene = [Sphere(CENTRE, RADIUS, sphere_color)]
    poses = [look_at(CENTRE + [1.4, 0.3, 0.6], CENTRE), look_at(CENTRE + [-1.2, -0.2, 0.9], CENTRE)]
    views = [registered_view(scene, intrinsics(), pose) for pose in poses]
    reported: list[float] = []
    colors = colorize(vertices, normals, views, progress=reported.append)
    assert reported == [0.5, 1.0]
    seen = well_seen(vertices, normals, poses)
    assert 0.3 < seen.mean() < 0.9  # the test means something: some vertices are unseen
    error = np.abs(colors[seen].astype(float) - sphere_color(vertices[seen]))
    assert error.max() <= 4.0
    assert error.mean() <= 1.0
    # Unseen vertices took the colour of a seen neighbour: close to the surface colour there.
    unseen_error = np.abs(colors[~seen].astype(float) - sphere_color(vertices[~seen]))
    assert np.median(unseen_error) < 60


def test_plane_seen_by_two_cameras() -> None:
    vertices, normals = plane_grid()
    scene = [Rect(np.array([0.0, 1.0, 0.0]), np.array([0.6, 0, 0]), np.array([0, 0.6, 0]),
                  plane_color)]
    poses = [look_at([0.4, 1.2, 1.5], [0, 1, 0]), look_at([-0.5, 0.8, 1.4], [0, 1, 0])]
    views = [registered_view(scene, intrinsics(), pose) for pose in poses]
    error = np.abs(colorize(vertices, normals, views).astype(float) - plane_color(vertices))
    assert error.max() <= 2.0


@settings(max_examples=15, deadline=None)
@given(
    rgb=st.tuples(*[st.integers(0, 255)] * 3),
    azimuths=st.lists(st.floats(0, 2 * np.pi), min_size=1, max_size=3),
    elevation=st.floats(-1.0, 1.0),
    distance=st.floats(0.8, 3.0),
)
def test_uniform_sphere_gets_exactly_its_colour_from_any_cameras(
    rgb: tuple[int, int, int], azimuths: list[float], elevation: float, distance: float
) -> None:
    vertices, normals = sphere_mesh(subdivisions=2)
    scene = [Sphere(CENTRE, RADIUS, lambda p: np.tile(np.array(rgb, float), (len(p), 1)))]
    views = []
    for azimuth in azimuths:
        direction = np.array([np.cos(azimuth) * np.cos(elevation), np.sin(elevation),
                              np.sin(azimuth) * np.cos(elevation)])
        views.append(registered_view(scene, intrinsics(96, 72, 90.0),
                                     look_at(CENTRE + distance * direction, CENTRE)))
    colors = colorize(vertices, normals, views)
    # Silhouette pixels are black background: exactness shows none bled in.
    np.testing.assert_array_equal(colors, np.tile(np.array(rgb, np.uint8), (len(vertices), 1)))


# --- occlusion -------------------------------------------------------------------------------


def occlusion_scene() -> tuple[np.ndarray, np.ndarray, list[Sphere | Rect], np.ndarray,
                               np.ndarray]:
    vertices, normals = plane_grid()
    plane = Rect(np.array([0.0, 1.0, 0.0]), np.array([0.6, 0, 0]), np.array([0, 0.6, 0]),
                 plane_color)
    # A red card 0.5 m in front of the plane, not part of the mesh (a hand, a cable...).
    card = Rect(np.array([0.2, 1.0, 0.5]), np.array([0.12, 0, 0]), np.array([0, 0.15, 0]),
                lambda p: np.tile(RED, (len(p), 1)))
    pose_a = look_at([0.4, 1.0, 1.5], [0.0, 1.0, 0.0])  # the card hides part of the plane
    pose_b = look_at([-0.9, 1.1, 1.3], [0.0, 1.0, 0.0])
    return vertices, normals, [plane, card], pose_a, pose_b


def hidden_from(vertices: np.ndarray, pose: np.ndarray,
                scene: Sequence[Sphere | Rect]) -> np.ndarray:
    dirs = vertices - pose[:3, 3]
    t_card = scene[1].hit(pose[:3, 3], dirs)
    return t_card < 1.0


def test_occluded_vertices_take_no_colour_from_the_occluded_camera() -> None:
    vertices, normals, scene, pose_a, pose_b = occlusion_scene()
    hidden = hidden_from(vertices, pose_a, scene)
    assert hidden.sum() > 20 and not hidden_from(vertices, pose_b, scene).any()
    views = [registered_view(scene, intrinsics(), pose) for pose in (pose_a, pose_b)]
    error = np.abs(colorize(vertices, normals, views).astype(float) - plane_color(vertices))
    assert error.max() <= 2.0
    # Control: without camera A's depth image the hidden vertices take the card's red.
    blind = [ColorView(views[0].image_rgb, views[0].intrinsics, views[0].world_from_camera),
             views[1]]
    blind_error = np.abs(colorize(vertices, normals, blind).astype(float) - plane_color(vertices))
    assert np.median(blind_error[hidden].max(axis=1)) > 40


def test_vertices_no_camera_sees_take_the_nearest_seen_colour() -> None:
    vertices, normals, scene, pose_a, _ = occlusion_scene()
    view = registered_view(scene, intrinsics(), pose_a)
    hidden = hidden_from(vertices, pose_a, scene)
    colors = colorize(vertices, normals, [view]).astype(float)
    # No red leaks in: every hidden vertex copies a plane colour from around the card's shadow.
    assert np.all(colors[hidden, 0] < 200) and np.all(colors[hidden, 1] > 150)
    error = np.abs(colors[~hidden] - plane_color(vertices[~hidden]))
    assert np.percentile(error, 95) <= 2.0
    # Nothing seen at all: the configured fallback.
    away = ColorView(view.image_rgb, view.intrinsics, look_at([0, 1, 1.5], [0, 1, 5]),
                     view.depth_m)
    config = ColorizeConfig(fallback_rgb=(1, 2, 3))
    assert np.all(colorize(vertices, normals, [away], config) == [1, 2, 3])


# --- colour not registered to depth, distortion ----------------------------------------------


def unregistered_view(distortion: tuple[float, ...]) -> tuple[View, list[Sphere | Rect]]:
    scene: list[Sphere | Rect] = [Sphere(CENTRE, RADIUS, sphere_color)]
    # Aimed beside the sphere so that it lies off-axis, where the lens bends most.
    world_from_depth = look_at(CENTRE + [0.2, 0.4, 1.3], CENTRE + [0.2, 0.15, 0.0])
    color_from_depth = np.eye(4)
    color_from_depth[:3, :3] = cv2.Rodrigues(np.array([0.02, -0.1, 0.01]))[0]
    color_from_depth[:3, 3] = [-0.032, 0.002, 0.004]
    depth_model = intrinsics(128, 128, 110.0)
    color_model = intrinsics(200, 150, 170.0, distortion)
    depth, _ = render(scene, depth_model, world_from_depth)
    _, rgb = render(scene, color_model, world_from_depth @ np.linalg.inv(color_from_depth))
    camera = CameraInfo("cam0", depth_model, color_model, color_from_depth, world_from_depth)
    return View(camera, 0, depth, rgb), scene


@pytest.mark.parametrize("distortion", [(), (-0.25, 0.08, 0.001, -0.002, 0.0)])
def test_unregistered_and_distorted_colour_is_sampled_in_its_own_camera(
    distortion: tuple[float, ...],
) -> None:
    view, _ = unregistered_view(distortion)
    vertices, normals = sphere_mesh()
    color_view = ColorView.from_view(view)
    assert color_view.world_from_depth is not None
    colors = colorize(vertices, normals, [color_view])
    seen = well_seen(vertices, normals, [color_view.world_from_camera], 0.4)
    error = np.abs(colors[seen].astype(float) - sphere_color(vertices[seen]))
    assert error.max() <= 4.0
    # Controls: sampling colour from the depth camera's pose, or ignoring the lens, is wrong.
    wrong_pose = ColorView(color_view.image_rgb, color_view.intrinsics,
                           color_view.world_from_depth, view.depth_m, color_view.depth_intrinsics,
                           color_view.world_from_depth)
    wrong = np.abs(colorize(vertices, normals, [wrong_pose])[seen] - sphere_color(vertices[seen]))
    assert wrong.max() > 15
    if distortion:
        pinhole = ColorView(color_view.image_rgb,
                            intrinsics(200, 150, 170.0), color_view.world_from_camera,
                            view.depth_m, color_view.depth_intrinsics, color_view.world_from_depth)
        lens = np.abs(colorize(vertices, normals, [pinhole])[seen] - sphere_color(vertices[seen]))
        assert lens.max() > 15


def test_colorize_mesh_computes_normals_when_absent() -> None:
    ico = trimesh.creation.icosphere(subdivisions=3)
    mesh = TriangleMesh(CENTRE + RADIUS * np.asarray(ico.vertices),
                        np.asarray(ico.faces, dtype=np.int32))
    pose = look_at(CENTRE + [0, 0, 1.5], CENTRE)
    out = colorize_mesh(mesh, [registered_view([Sphere(CENTRE, RADIUS, sphere_color)],
                                               intrinsics(), pose)])
    assert out.vertex_colors is not None and out.vertex_colors.shape == (mesh.vertex_count, 3)
    assert out.faces is mesh.faces
    front = mesh.vertices_m[:, 2] - CENTRE[2] > 0.15
    error = np.abs(out.vertex_colors[front].astype(float) - sphere_color(mesh.vertices_m[front]))
    assert error.max() <= 4.0


# --- bad input -------------------------------------------------------------------------------


def test_bad_inputs_are_refused_naming_the_field() -> None:
    model = intrinsics(16, 12, 10.0)
    image = np.zeros((12, 16, 3), np.uint8)
    with pytest.raises(ValueError, match="image_rgb"):
        ColorView(np.zeros((12, 16), np.uint8), model, np.eye(4))
    with pytest.raises(ValueError, match="image_rgb"):
        ColorView(np.zeros((13, 16, 3), np.uint8), model, np.eye(4))
    with pytest.raises(ValueError, match="world_from_camera"):
        ColorView(image, model, np.eye(3))
    with pytest.raises(ValueError, match="depth_m"):
        ColorView(image, model, np.eye(4), np.zeros((5, 5), np.float32))
    with pytest.raises(ValueError, match="depth_intrinsics"):
        ColorView(image, model, np.eye(4), np.zeros((12, 16), np.float32), model)
    camera = CameraInfo("c", model)
    with pytest.raises(ValueError, match="world_from_depth"):
        ColorView.from_view(View(camera, 0, np.zeros((12, 16), np.float32), image))
    with pytest.raises(ValueError, match="colour"):
        ColorView.from_view(View(camera, 0, np.zeros((12, 16), np.float32)))
    view = ColorView(image, model, np.eye(4))
    with pytest.raises(ValueError, match="normals"):
        colorize(np.zeros((4, 3)), np.zeros((3, 3)), [view])
    with pytest.raises(ValueError, match="vertices_m"):
        colorize(np.full((4, 3), np.nan), np.zeros((4, 3)), [view])
    with pytest.raises(ValueError, match="views"):
        colorize(np.zeros((4, 3)), np.zeros((4, 3)), [])
    for field, kwargs in (("depth_tolerance_m", {"depth_tolerance_m": 0.0}),
                          ("min_cos", {"min_cos": 1.0}),
                          ("fallback_rgb", {"fallback_rgb": (0, 0, 300)})):
        with pytest.raises(ValueError, match=field):
            ColorizeConfig(**kwargs)  # type: ignore[arg-type]
