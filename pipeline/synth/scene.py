"""Whole synthetic captures: a mesh placed in the rig, rendered, made noisy, poses perturbed."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CameraInfo, CaptureMeta, FrameInfo, View
from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.synth.noise import KinectNoiseConfig, apply_kinect_noise, draw_depth_bias_m
from pipeline.synth.render import MeshRaycaster, albedo_colors, shade_color
from pipeline.synth.rig import RigConfig, rig_cameras
from pipeline.synth.shapes import snowman_mesh

Progress = Callable[[float], None]

_UP_ROTATIONS = {
    "+y": np.eye(3),
    "-y": np.diag([1.0, -1.0, -1.0]),
    "+z": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
    "-z": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "+x": np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]),
    "-x": np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]),
}
FRAME_PERIOD_US = 33_333
"""Time between frames, microseconds (the Azure Kinect runs at 30 frames per second)."""


@dataclass(frozen=True)
class SynthConfig:
    """What `synthesize` builds."""

    model_height_m: float = 1.8
    """Height the subject is scaled to, metres (unless `max_radius_m` makes it smaller)."""
    max_radius_m: float | None = 1.1
    """Largest horizontal distance of the subject from its vertical axis, metres: a model too
    wide at `model_height_m` (a cow, a teapot) is scaled down to fit inside the rig, where
    every camera still sees it in range. None: always `model_height_m`."""
    up_axis: str = "+y"
    """The mesh file's up axis (+x, -x, +y, -y, +z or -z), turned to world +Y."""
    yaw_deg: float = 0.0
    """Turn of the subject about world +Y after uprighting, degrees."""
    seed: int = 0
    """Seed of every random draw (noise, biases, pose errors)."""
    camera_count: int = 8
    """Cameras in the rig (spread over an upper and a lower ring)."""
    rig: RigConfig = field(default_factory=RigConfig)
    """Rig geometry; its camera_count and target_m are replaced from this config."""
    pose_error_rot_deg: float = 0.0
    """Rotation of each written extrinsic away from the truth, degrees (random axis)."""
    pose_error_trans_m: float = 0.0
    """Displacement of each written camera centre from the truth, metres (random direction)."""
    noise: bool = True
    """Apply the Azure Kinect noise model (False: ideal depth, exact to float32)."""
    noise_model: KinectNoiseConfig = field(default_factory=KinectNoiseConfig)
    """Parameters of the noise model."""
    frame_count: int = 1
    """Frames per camera (static subject; noise is drawn anew each frame)."""
    with_color: bool = True
    """Render registered colour images."""
    floor: bool = False
    """Render a floor plane at y = 0 too (never part of the ground truth)."""

    def __post_init__(self) -> None:
        if not self.model_height_m > 0:
            raise ValueError(f"model_height_m: must be positive, got {self.model_height_m}")
        if self.up_axis not in _UP_ROTATIONS:
            raise ValueError(f"up_axis: must be one of {sorted(_UP_ROTATIONS)}, "
                             f"got {self.up_axis!r}")
        if self.camera_count < 1:
            raise ValueError(f"camera_count: must be at least 1, got {self.camera_count}")
        if self.frame_count < 1:
            raise ValueError(f"frame_count: must be at least 1, got {self.frame_count}")
        if self.max_radius_m is not None and not self.max_radius_m > 0:
            raise ValueError(f"max_radius_m: must be positive, got {self.max_radius_m}")
        if self.pose_error_rot_deg < 0 or self.pose_error_trans_m < 0:
            raise ValueError("pose_error_rot_deg/pose_error_trans_m: must not be negative")

    def rig_config(self, subject_height_m: float | None = None) -> RigConfig:
        """The rig with this config's camera count, aimed at the subject's mid-height.

        subject_height_m: the placed subject's height (default `model_height_m`; it is less
        when `max_radius_m` scaled the subject down).
        """
        height = self.model_height_m if subject_height_m is None else subject_height_m
        return replace(self.rig, camera_count=self.camera_count,
                       target_m=(0.0, height / 2, 0.0))


def sample_mesh() -> TriangleMesh:
    """The built-in subject (a 1.8 m snowman, 61k triangles); needs no files."""
    return snowman_mesh()


def place_subject(mesh: TriangleMesh, config: SynthConfig) -> TriangleMesh:
    """The mesh uprighted, scaled to the height (or to `max_radius_m` if that is smaller),
    standing on y = 0, its bounding box centred on the vertical axis through the origin.

    Returns a world-frame mesh with vertex normals and procedural albedo vertex colours.
    """
    vertices = np.asarray(mesh.vertices_m, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise ValueError("mesh: vertices_m must be a non-empty (V, 3) array")
    if mesh.face_count == 0:
        raise ValueError("mesh: has no triangles")
    yaw = math.radians(config.yaw_deg)
    turn = np.array([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0],
                     [-math.sin(yaw), 0, math.cos(yaw)]])
    upright = vertices @ (turn @ _UP_ROTATIONS[config.up_axis]).T
    lo, hi = upright.min(axis=0), upright.max(axis=0)
    if hi[1] - lo[1] <= 0:
        raise ValueError(f"mesh: flat along its up axis {config.up_axis}, cannot scale it")
    offset = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    centred = upright - offset
    scale = config.model_height_m / (hi[1] - lo[1])
    if config.max_radius_m is not None:
        radius = float(np.hypot(centred[:, 0], centred[:, 2]).max())
        if radius * scale > config.max_radius_m:
            scale = config.max_radius_m / radius
    placed = centred * scale
    faces = np.asarray(mesh.faces, dtype=np.int32)
    return TriangleMesh(vertices_m=placed, faces=faces, vertex_colors=albedo_colors(placed),
                        vertex_normals=vertex_normals(placed, faces))


def true_cameras(ground_truth: TriangleMesh, config: SynthConfig) -> list[CameraInfo]:
    """The cameras with their TRUE poses for a subject placed by `place_subject`.

    `synthesize` renders with these; the capture it returns holds them plus the pose error.
    """
    height = float(np.max(ground_truth.vertices_m[:, 1]))
    return rig_cameras(config.rig_config(height))


def perturb_pose(world_from_depth: NDArray[np.float64], rot_deg: float, trans_m: float,
                 rng: np.random.Generator) -> NDArray[np.float64]:
    """The pose turned by exactly `rot_deg` about a random axis through the camera centre and
    moved by exactly `trans_m` in a random direction."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    angle = math.radians(rot_deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)
    pose = np.asarray(world_from_depth, dtype=np.float64).copy()
    pose[:3, :3] = pose[:3, :3] @ rotation
    pose[:3, 3] = pose[:3, 3] + trans_m * direction
    return pose


def _floor_mesh(half_size_m: float = 4.0) -> TriangleMesh:
    s = half_size_m
    vertices = np.array([[-s, 0, -s], [s, 0, -s], [s, 0, s], [-s, 0, s]], dtype=np.float64)
    return TriangleMesh(vertices_m=vertices, faces=np.array([[0, 2, 1], [0, 3, 2]], np.int32))


def _scene_mesh(subject: TriangleMesh, floor: bool) -> TriangleMesh:
    if not floor:
        return subject
    plane = _floor_mesh()
    return TriangleMesh(
        vertices_m=np.vstack([subject.vertices_m, plane.vertices_m]),
        faces=np.vstack([subject.faces, plane.faces + subject.vertex_count]).astype(np.int32))


def synthesize_stream(mesh: TriangleMesh, config: SynthConfig,
                      progress: Progress | None = None
                      ) -> tuple[CaptureMeta, Iterator[View], TriangleMesh]:
    """Like `synthesize`, but views are rendered lazily (camera by camera) as they are taken.

    `progress` gets the fraction of cameras done, 0..1, as the iterator advances.
    """
    subject = place_subject(mesh, config)
    cameras = true_cameras(subject, config)
    pose_rng, _, noise_rng = np.random.default_rng(config.seed).spawn(3)
    written = []
    for cam in cameras:
        assert cam.world_from_depth is not None
        pose = perturb_pose(cam.world_from_depth, config.pose_error_rot_deg,
                            config.pose_error_trans_m, pose_rng)
        written.append(replace(cam, world_from_depth=pose))
    biases = camera_depth_biases_m(config, len(cameras))
    frames = tuple(FrameInfo(index=i, timestamp_us=i * FRAME_PERIOD_US)
                   for i in range(config.frame_count))
    meta = CaptureMeta(depth_scale=0.001, cameras=tuple(written), frames=frames)
    caster = MeshRaycaster(_scene_mesh(subject, config.floor))

    def views() -> Iterator[View]:
        for index, (true_cam, cam) in enumerate(zip(cameras, written, strict=True)):
            yield from _camera_views(caster, true_cam, cam, biases[index], config, noise_rng)
            if progress is not None:
                progress((index + 1) / len(cameras))

    return meta, views(), subject


def camera_depth_biases_m(config: SynthConfig, camera_count: int) -> list[float]:
    """Each camera's constant range offset, metres, as `synthesize` draws it for `config`
    (what the `align` stage estimates)."""
    bias_rng = np.random.default_rng(config.seed).spawn(3)[1]
    return [draw_depth_bias_m(config.noise_model, bias_rng) for _ in range(camera_count)]


def _camera_views(caster: MeshRaycaster, true_cam: CameraInfo, written_cam: CameraInfo,
                  bias_m: float, config: SynthConfig, rng: np.random.Generator
                  ) -> Iterator[View]:
    assert true_cam.world_from_depth is not None
    intrinsics = true_cam.depth_intrinsics
    rendering = caster.render(intrinsics, true_cam.world_from_depth)
    color = shade_color(rendering) if config.with_color else None
    for frame in range(config.frame_count):
        if config.noise:
            depth = apply_kinect_noise(rendering.depth_m, rendering.normals_cam, intrinsics,
                                       config.noise_model, rng, bias_m)
        else:
            depth = rendering.depth_m.copy()
        yield View(camera=written_cam, frame_index=frame, depth_m=depth, color_rgb=color)


def synthesize(mesh: TriangleMesh, config: SynthConfig, progress: Progress | None = None
               ) -> tuple[CaptureMeta, list[View], TriangleMesh]:
    """A synthetic capture of `mesh` as the rig of `config` sees it.

    Returns (meta, views, ground_truth): meta holds the WRITTEN extrinsics (true poses plus
    the configured pose error); views are camera-major, every frame of cam0 first; the ground
    truth is the subject in world coordinates (metres, +Y up, on y = 0) with vertex normals and
    albedo colours. Rendering always uses the true poses.
    """
    meta, views, ground_truth = synthesize_stream(mesh, config, progress)
    return meta, list(views), ground_truth
