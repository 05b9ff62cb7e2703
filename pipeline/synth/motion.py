"""Synthetic sequences: the subject filmed for many frames, static, under a rigid motion or
an articulated one, with the ground truth of every frame.

A rigid motion turns the subject about the vertical axis through the origin and sways it
side to side (along world x). Rendering the moved subject from a camera equals rendering the
subject where it stands from the camera moved by the inverse motion, so each frame is cast
against one prepared mesh; the texture then moves with the subject, as a real one would.
An articulated motion bends the subject's upper part forwards and back about a horizontal
joint (a bow), blended over a band around the joint so the surface stays closed; each frame's
bent mesh is cast on its own. Sensor noise is drawn anew for every frame; each camera keeps
its depth bias throughout.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CameraInfo, CaptureMeta, FrameInfo, View
from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.synth.noise import apply_kinect_noise, draw_depth_bias_m
from pipeline.synth.render import MeshRaycaster, Rendering, shade_color
from pipeline.synth.scene import SynthConfig, perturb_pose, place_subject, true_cameras

Progress = Callable[[float], None]
MOTIONS = ("static", "rigid", "articulated")


@dataclass(frozen=True)
class MotionConfig:
    """How the subject moves over a sequence and how fast it is filmed."""

    kind: str = "static"
    """static (the same pose every frame), rigid (turn plus sway) or articulated (a bow)."""
    frame_rate_hz: float = 30.0
    """Frames per second of the capture (its frame timestamps)."""
    turn_deg_per_s: float = 60.0
    """Rigid: turn about the vertical axis, degrees per second."""
    sway_amplitude_m: float = 0.1
    """Rigid: largest side-to-side displacement along world x, metres."""
    sway_frequency_hz: float = 0.5
    """Rigid: side-to-side cycles per second."""
    bow_amplitude_deg: float = 25.0
    """Articulated: largest bend of the upper part about the joint, degrees."""
    bow_frequency_hz: float = 0.5
    """Articulated: bows per second."""
    joint_height_share: float = 0.5
    """Articulated: the joint's height as a share of the subject's height."""
    joint_blend_m: float = 0.15
    """Articulated: height of the band over which the bend fades in around the joint, metres."""

    def __post_init__(self) -> None:
        if self.kind not in MOTIONS:
            raise ValueError(f"kind: must be one of {', '.join(MOTIONS)}, got {self.kind!r}")
        if not 0 < self.frame_rate_hz <= 240:
            raise ValueError(f"frame_rate_hz: must be in (0, 240], got {self.frame_rate_hz}")
        if self.sway_amplitude_m < 0 or self.sway_frequency_hz < 0:
            raise ValueError("sway_amplitude_m/sway_frequency_hz: must not be negative")
        if not 0 < self.joint_height_share < 1 or not self.joint_blend_m > 0:
            raise ValueError("joint_height_share: must be in (0, 1); joint_blend_m: positive")

    @property
    def frame_period_us(self) -> int:
        return round(1e6 / self.frame_rate_hz)


def bow_rad(motion: MotionConfig, time_s: float) -> float:
    """The articulated bend at ``time_s``, radians (0 for other motions)."""
    if motion.kind != "articulated":
        return 0.0
    return math.radians(motion.bow_amplitude_deg) * math.sin(
        2 * math.pi * motion.bow_frequency_hz * time_s)


def bend(vertices_m: NDArray[np.float64], angle_rad: float, joint_y_m: float,
         blend_m: float) -> NDArray[np.float64]:
    """Vertices above the joint turned about the horizontal x axis through (0, joint_y_m, 0);
    the turn fades in linearly across ``blend_m`` around the joint."""
    weight = np.clip((vertices_m[:, 1] - joint_y_m) / blend_m + 0.5, 0.0, 1.0)
    angle = angle_rad * weight
    y, z = vertices_m[:, 1] - joint_y_m, vertices_m[:, 2]
    out = vertices_m.copy()
    out[:, 1] = joint_y_m + y * np.cos(angle) - z * np.sin(angle)
    out[:, 2] = y * np.sin(angle) + z * np.cos(angle)
    return out


def world_from_subject(motion: MotionConfig, time_s: float) -> NDArray[np.float64]:
    """(4, 4) pose of the subject at ``time_s``: where its standing pose is carried to."""
    pose = np.eye(4)
    if motion.kind != "rigid":
        return pose
    yaw = math.radians(motion.turn_deg_per_s * time_s)
    pose[:3, :3] = np.array([[math.cos(yaw), 0.0, math.sin(yaw)], [0.0, 1.0, 0.0],
                             [-math.sin(yaw), 0.0, math.cos(yaw)]])
    pose[0, 3] = motion.sway_amplitude_m * math.sin(2 * math.pi * motion.sway_frequency_hz
                                                    * time_s)
    return pose


@dataclass(frozen=True)
class SequenceTruth:
    """The ground truth of every frame: the placed subject and its pose per frame."""

    subject: TriangleMesh
    """The subject standing at the origin (frame 0 of a static sequence), world frame."""
    world_from_subject: NDArray[np.float64]
    """(N, 4, 4) the subject's pose in each frame."""
    bow_rad: NDArray[np.float64] | None = None
    """(N,) the articulated bend in each frame, radians; None: the subject does not bend."""
    joint_y_m: float = 0.0
    """Height of the articulated joint, metres."""
    joint_blend_m: float = 0.15
    """Height of the band the bend fades in over, metres."""

    @property
    def frame_count(self) -> int:
        return int(self.world_from_subject.shape[0])

    def mesh(self, frame: int) -> TriangleMesh:
        """The subject as it stands in ``frame`` (world frame, metres)."""
        pose = self.world_from_subject[frame]
        vertices = self.subject.vertices_m
        if self.bow_rad is not None:
            vertices = bend(vertices, float(self.bow_rad[frame]), self.joint_y_m,
                            self.joint_blend_m)
        vertices = vertices @ pose[:3, :3].T + pose[:3, 3]
        faces = self.subject.faces
        return TriangleMesh(vertices_m=vertices, faces=faces,
                            vertex_colors=self.subject.vertex_colors,
                            vertex_normals=vertex_normals(vertices, faces))


def synthesize_sequence(mesh: TriangleMesh, config: SynthConfig, motion: MotionConfig,
                        progress: Progress | None = None, *, by_frame: bool = False,
                        first_frame: int = 0
                        ) -> tuple[CaptureMeta, Iterator[View], SequenceTruth]:
    """A capture of ``config.frame_count`` frames of the subject under ``motion``; views are
    rendered lazily, camera by camera (frame by frame for an articulated motion, or with
    ``by_frame``: a stream's order, each frame-set whole before the next; ``progress`` gets
    the fraction done). The views start at ``first_frame`` (a stream resumed part-way); the
    capture's meta and truth still describe every frame."""
    if config.floor and motion.kind != "static":
        raise ValueError("floor: a moving subject is rendered without a floor")
    if not 0 <= first_frame <= config.frame_count:
        raise ValueError(f"first_frame: must be in [0, {config.frame_count}], got {first_frame}")
    subject = place_subject(mesh, config)
    cameras = true_cameras(subject, config)
    pose_rng, bias_rng, noise_rng = np.random.default_rng(config.seed).spawn(3)
    written = [_written(cam, config, pose_rng) for cam in cameras]
    biases = [draw_depth_bias_m(config.noise_model, bias_rng) for _ in cameras]
    times_s = [i / motion.frame_rate_hz for i in range(config.frame_count)]
    poses = np.stack([world_from_subject(motion, t) for t in times_s])
    frames = tuple(FrameInfo(index=i, timestamp_us=i * motion.frame_period_us)
                   for i in range(config.frame_count))
    meta = CaptureMeta(depth_scale=0.001, cameras=tuple(written), frames=frames)
    height_m = float(subject.vertices_m[:, 1].max())
    truth = SequenceTruth(
        subject=subject, world_from_subject=poses,
        bow_rad=np.array([bow_rad(motion, t) for t in times_s])
        if motion.kind == "articulated" else None,
        joint_y_m=motion.joint_height_share * height_m, joint_blend_m=motion.joint_blend_m)
    if truth.bow_rad is not None:
        return meta, _bent_views(truth, cameras, written, biases, config, noise_rng,
                                 progress, first_frame), truth
    caster = MeshRaycaster(subject)
    renderings: list[Rendering | None] = [None] * len(cameras)

    def view(index: int, frame: int) -> View:
        rendering = renderings[index]
        if rendering is None or motion.kind != "static":  # static: one rendering a camera
            rendering = renderings[index] = _render(caster, cameras[index], poses[frame])
        return _view(rendering, cameras[index], written[index], frame, biases[index], config,
                     noise_rng)

    def views() -> Iterator[View]:
        for index in range(len(cameras)):
            for frame in range(first_frame, config.frame_count):
                yield view(index, frame)
            renderings[index] = None  # done with this camera: hold one rendering at a time
            if progress is not None:
                progress((index + 1) / len(cameras))

    def views_by_frame() -> Iterator[View]:
        for frame in range(first_frame, config.frame_count):
            for index in range(len(cameras)):
                yield view(index, frame)
            if progress is not None:
                progress((frame + 1) / config.frame_count)

    return meta, views_by_frame() if by_frame else views(), truth


def _bent_views(truth: SequenceTruth, cameras: list[CameraInfo], written: list[CameraInfo],
                biases: list[float], config: SynthConfig, rng: np.random.Generator,
                progress: Progress | None, first_frame: int) -> Iterator[View]:
    """Frame by frame: each frame's bent subject is a mesh of its own to cast against."""
    identity = np.eye(4)
    for frame in range(first_frame, truth.frame_count):
        caster = MeshRaycaster(truth.mesh(frame))
        for index, (true_cam, cam) in enumerate(zip(cameras, written, strict=True)):
            yield _view(_render(caster, true_cam, identity), true_cam, cam, frame,
                        biases[index], config, rng)
        if progress is not None:
            progress((frame + 1) / truth.frame_count)


def _written(cam: CameraInfo, config: SynthConfig, rng: np.random.Generator) -> CameraInfo:
    assert cam.world_from_depth is not None
    return replace(cam, world_from_depth=perturb_pose(
        cam.world_from_depth, config.pose_error_rot_deg, config.pose_error_trans_m, rng))


def _render(caster: MeshRaycaster, true_cam: CameraInfo,
            world_from_subject_pose: NDArray[np.float64]) -> Rendering:
    assert true_cam.world_from_depth is not None
    # The camera as the standing subject sees it once the subject has moved.
    subject_from_depth = np.linalg.inv(world_from_subject_pose) @ true_cam.world_from_depth
    return caster.render(true_cam.depth_intrinsics, subject_from_depth)


def _view(rendering: Rendering, true_cam: CameraInfo, written_cam: CameraInfo, frame: int,
          bias_m: float, config: SynthConfig, rng: np.random.Generator) -> View:
    color = shade_color(rendering) if config.with_color else None
    if config.noise:
        depth = apply_kinect_noise(rendering.depth_m, rendering.normals_cam,
                                   true_cam.depth_intrinsics, config.noise_model, rng, bias_m)
    else:
        depth = rendering.depth_m.copy()
    return View(camera=written_cam, frame_index=frame, depth_m=depth, color_rgb=color)
