"""Synthetic calibration captures: a ChArUco target moved through the rig's volume.

The target is one flat board (``plane``), turned over the frames to face every part of the
ring, or a cube with a board on each face (``cube``). Colour images are rendered like an Azure
Kinect's colour camera: higher resolution than depth, own intrinsics with lens distortion and a
``color_from_depth`` offset; boards are warped in by their plane homography with supersampling,
then lit, blurred and noised. Depth images are ray cast and passed through the rig's noise model.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.capture import BoardSpec, CameraInfo, CaptureMeta, FrameInfo, Intrinsics, Target, View
from pipeline.geometry.mesh import TriangleMesh
from pipeline.synth.noise import KinectNoiseConfig, apply_kinect_noise, draw_depth_bias_m
from pipeline.synth.render import MeshRaycaster, lambert_shading
from pipeline.synth.rig import RigConfig, rig_cameras

Matrix = NDArray[np.float64]
_SOURCE_PX_PER_SQUARE = 64
_PAPER, _INK = 235.0, 25.0


@dataclass(frozen=True)
class TargetSynthConfig:
    """What a synthetic calibration capture holds."""

    kind: str = "plane"
    """``plane``: one board moved and turned through the volume; ``cube``: a board per face."""
    frame_count: int = 24
    """Frames of the capture (target poses)."""
    camera_count: int = 8
    """Cameras of the default rig (ignored when cameras are passed in)."""
    seed: int = 0
    """Seed of the target motion and of every noise draw."""
    color_width: int = 1280
    """Colour image width, pixels (Azure Kinect 720p mode)."""
    color_height: int = 720
    """Colour image height, pixels."""
    color_fov_x_deg: float = 90.0
    """Horizontal field of view of the colour camera, degrees (Azure Kinect: 90)."""
    color_distortion: tuple[float, ...] = (0.04, -0.03, 0.0005, -0.0003, 0.0)
    """Colour lens distortion, OpenCV order (k1, k2, p1, p2, k3)."""
    color_noise_sigma: float = 2.0
    """Standard deviation of the colour image noise, grey levels."""
    blur_sigma_px: float = 0.6
    """Gaussian blur of the colour optics, pixels."""
    supersample: int = 3
    """Supersampling factor of the board warps (anti-aliasing)."""
    depth_noise: bool = True
    """Pass depth through the Azure Kinect noise model (False: ideal depth)."""
    noise_model: KinectNoiseConfig = field(default_factory=KinectNoiseConfig)
    """Parameters of the depth noise model."""
    square_length_m: float = 0.08
    """ChArUco square side, metres."""
    marker_length_m: float = 0.06
    """ArUco marker side, metres."""
    dictionary: str = "DICT_5X5_100"
    """ArUco dictionary of the boards."""

    def __post_init__(self) -> None:
        if self.kind not in ("plane", "cube"):
            raise ValueError(f"target kind must be 'plane' or 'cube', got {self.kind!r}")
        if self.frame_count < 1:
            raise ValueError(f"frame_count: must be at least 1, got {self.frame_count}")
        if self.supersample < 1:
            raise ValueError("supersample: must be at least 1")


@dataclass(frozen=True)
class _Face:
    """One printed plate: a board with a white margin, in the target frame."""

    board: BoardSpec
    margin_m: tuple[float, float]
    image: NDArray[np.uint8]
    """Printed grey image incl. margin; pixel (u, v) covers board ((u, v) + 0.5) / px_per_m."""
    px_per_m: float

    def size_m(self) -> tuple[float, float]:
        return (self.board.squares_x * self.board.square_length_m + 2 * self.margin_m[0],
                self.board.squares_y * self.board.square_length_m + 2 * self.margin_m[1])

    def corners_board(self) -> Matrix:
        """(4, 3) plate corners in the board frame (margin included)."""
        w, h = self.size_m()
        x0, y0 = -self.margin_m[0], -self.margin_m[1]
        return np.array([[x0, y0, 0], [x0 + w, y0, 0], [x0 + w, y0 + h, 0], [x0, y0 + h, 0]])


def _axes_facing(normal: Matrix, up: Matrix) -> Matrix:
    """Board rotation whose printed face looks along ``normal`` with image-down against ``up``."""
    z = -normal / np.linalg.norm(normal)
    y = -(up - np.dot(up, z) * z)
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


def _board_spec(config: TargetSynthConfig, squares: tuple[int, int], first_id: int,
                target_from_board: Matrix) -> BoardSpec:
    return BoardSpec(dictionary=config.dictionary, squares_x=squares[0], squares_y=squares[1],
                     square_length_m=config.square_length_m,
                     marker_length_m=config.marker_length_m, first_marker_id=first_id,
                     target_from_board=target_from_board)


def make_target(config: TargetSynthConfig) -> tuple[Target, tuple[tuple[float, float], ...]]:
    """The target of a config and each board's white margin (x, y), metres."""
    if config.kind == "plane":
        board = _board_spec(config, (8, 6), 0, np.eye(4))
        return Target(boards=(board,)), ((0.04, 0.04),)
    squares = 5
    board_m = squares * config.square_length_m
    side = board_m + 0.05
    boards = []
    normals = [(0, 0, 1), (1, 0, 0), (0, 0, -1), (-1, 0, 0), (0, 1, 0), (0, -1, 0)]
    for index, n in enumerate(normals):
        normal = np.array(n, dtype=float)
        up = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.5 else np.array([0, 0, -normal[1]])
        rotation = _axes_facing(normal, up)
        centre_board = np.array([board_m / 2, board_m / 2, 0.0])
        pose = np.eye(4)
        pose[:3, :3] = rotation
        pose[:3, 3] = normal * side / 2 - rotation @ centre_board
        boards.append(_board_spec(config, (squares, squares), index * (squares * squares // 2),
                                  pose))
    margin = (side - board_m) / 2
    return Target(boards=tuple(boards)), ((margin, margin),) * len(boards)


def _faces(target: Target, margins: Sequence[tuple[float, float]]) -> list[_Face]:
    from pipeline.calibration.detection import charuco_board

    faces = []
    for board, margin in zip(target.boards, margins, strict=True):
        px_per_m = _SOURCE_PX_PER_SQUARE / board.square_length_m
        size = (board.squares_x * _SOURCE_PX_PER_SQUARE, board.squares_y * _SOURCE_PX_PER_SQUARE)
        board_image = charuco_board(board).generateImage(size, marginSize=0, borderBits=1)
        mx, my = (round(m * px_per_m) for m in margin)
        printed = np.asarray(cv2.copyMakeBorder(board_image, my, my, mx, mx,
                                                cv2.BORDER_CONSTANT, value=255), np.uint8)
        faces.append(_Face(board=board, margin_m=(mx / px_per_m, my / px_per_m), image=printed,
                           px_per_m=px_per_m))
    return faces


def _neighbour_midpoints(camera_centres: Sequence[Matrix], centre_m: Matrix) -> list[Matrix]:
    """Points midway between cameras adjacent in azimuth about ``centre_m`` (an operator aims
    the board at such a pair so both see it well)."""
    offsets = [c - centre_m for c in camera_centres]
    order = np.argsort([math.atan2(o[0], o[2]) for o in offsets])
    ordered = [camera_centres[i] for i in order]
    if len(ordered) == 1:
        return ordered
    return [(a + b) / 2 for a, b in zip(ordered, ordered[1:] + ordered[:1], strict=True)]


def target_trajectory(config: TargetSynthConfig, centre_m: Matrix,
                      camera_centres: Sequence[Matrix], rng: np.random.Generator
                      ) -> list[Matrix]:
    """``world_from_target`` per frame, wandering about ``centre_m``: the plane faces one pair
    of neighbouring cameras after another (upper and lower ring interleave, so every pair
    joins the two rings) with some wobble; the cube tumbles."""
    aims = _neighbour_midpoints(list(camera_centres), centre_m)
    poses = []
    for frame in range(config.frame_count):
        position = centre_m + rng.uniform([-0.25, -0.25, -0.25], [0.25, 0.3, 0.25])
        pose = np.eye(4)
        if config.kind == "plane":
            normal = aims[frame % len(aims)] - position
            normal = normal / np.linalg.norm(normal) + rng.normal(0.0, 0.12, 3)
            rotation = _axes_facing(normal, np.array([0.0, 1.0, 0.0]))
            roll = math.radians(rng.uniform(-25, 25))
            rotation = rotation @ cv2.Rodrigues(np.array([0.0, 0.0, roll]))[0]
            centre_board = np.array([4 * config.square_length_m, 3 * config.square_length_m, 0])
            pose[:3, :3] = rotation
            pose[:3, 3] = position - rotation @ centre_board
        else:
            turn = np.array([0.0, rng.uniform(0, 2 * math.pi), 0.0])
            tilt = np.radians(rng.uniform(-25, 25, size=3)) * np.array([1.0, 0.0, 1.0])
            pose[:3, :3] = cv2.Rodrigues(turn)[0] @ cv2.Rodrigues(tilt)[0]
            pose[:3, 3] = position
        poses.append(pose)
    return poses


def with_kinect_color(camera: CameraInfo, config: TargetSynthConfig) -> CameraInfo:
    """The camera with an Azure Kinect-like colour camera (6 degrees tilt, 32 mm offset)."""
    if camera.color_intrinsics is not None and camera.color_from_depth is not None:
        return camera
    f = (config.color_width / 2) / math.tan(math.radians(config.color_fov_x_deg) / 2)
    intrinsics = Intrinsics(width=config.color_width, height=config.color_height, fx=f,
                            fy=f * 1.0008, cx=(config.color_width - 1) / 2 + 3.1,
                            cy=(config.color_height - 1) / 2 - 4.3,
                            distortion=tuple(config.color_distortion))
    color_from_depth = np.eye(4)
    color_from_depth[:3, :3] = cv2.Rodrigues(np.array([math.radians(-6.0), 0.002, -0.001]))[0]
    color_from_depth[:3, 3] = (-0.032, -0.0021, 0.0039)
    return replace(camera, color_intrinsics=intrinsics, color_from_depth=color_from_depth)


def _plates_mesh(faces: Sequence[_Face], world_from_target: Matrix) -> TriangleMesh:
    vertices, triangles = [], []
    for index, face in enumerate(faces):
        world_from_board = world_from_target @ face.board.target_from_board
        corners = face.corners_board() @ world_from_board[:3, :3].T + world_from_board[:3, 3]
        vertices.append(corners)
        triangles += [[4 * index, 4 * index + 1, 4 * index + 2],
                      [4 * index, 4 * index + 2, 4 * index + 3]]
    return TriangleMesh(vertices_m=np.concatenate(vertices),
                        faces=np.array(triangles, dtype=np.int32))


def _distortion_maps(intrinsics: Intrinsics) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """For every pixel of the distorted image, where it lies in the ideal pinhole image."""
    grid = np.stack(np.meshgrid(np.arange(intrinsics.width, dtype=np.float64),
                                np.arange(intrinsics.height, dtype=np.float64)), axis=-1)
    matrix = intrinsics.matrix()
    ideal = cv2.undistortPoints(grid.reshape(-1, 1, 2), matrix, intrinsics.distortion_coeffs(),
                                P=matrix, criteria=(cv2.TERM_CRITERIA_COUNT
                                                    | cv2.TERM_CRITERIA_EPS, 30, 1e-9))
    ideal = np.asarray(ideal, np.float32).reshape(intrinsics.height, intrinsics.width, 2)
    return ideal[..., 0].copy(), ideal[..., 1].copy()


class _ColorRenderer:
    def __init__(self, camera: CameraInfo, world_from_depth: Matrix, config: TargetSynthConfig,
                 maps_cache: dict[Intrinsics, tuple[NDArray[np.float32], NDArray[np.float32]]]):
        assert camera.color_intrinsics is not None and camera.color_from_depth is not None
        self.intrinsics = camera.color_intrinsics
        self.color_from_world = camera.color_from_depth @ np.linalg.inv(world_from_depth)
        self.config = config
        self.maps = None
        if self.intrinsics.has_distortion:
            if self.intrinsics not in maps_cache:
                maps_cache[self.intrinsics] = _distortion_maps(self.intrinsics)
            self.maps = maps_cache[self.intrinsics]

    def render(self, faces: Sequence[_Face], world_from_target: Matrix,
               rng: np.random.Generator) -> NDArray[np.uint8]:
        intr, k = self.intrinsics, self.config.supersample
        height, width = intr.height, intr.width
        # A dim studio wall with a lighting gradient behind the target.
        ramp = np.linspace(0.0, 1.0, width, dtype=np.float32)[None, :]
        image = np.broadcast_to(70.0 + 40.0 * ramp, (height, width)).astype(np.float32)
        for face in faces:
            world_from_board = world_from_target @ face.board.target_from_board
            color_from_board = self.color_from_world @ world_from_board
            corners = face.corners_board() @ color_from_board[:3, :3].T + color_from_board[:3, 3]
            centre = corners.mean(axis=0)
            # Only the printed side shows, and not at grazing angles.
            facing = color_from_board[:3, 2] @ centre / np.linalg.norm(centre)
            if corners[:, 2].min() <= 0.05 or facing < 0.15:
                continue
            projected = corners @ intr.matrix().T
            projected = projected[:, :2] / projected[:, 2:3]
            x0, y0 = np.maximum(np.floor(projected.min(axis=0)).astype(int) - 2, 0)
            x1, y1 = np.minimum(np.ceil(projected.max(axis=0)).astype(int) + 2,
                                [width - 1, height - 1])
            if x1 <= x0 or y1 <= y0:
                continue
            s = 1.0 / face.px_per_m
            source_to_board = np.array([[s, 0, 0.5 * s - face.margin_m[0]],
                                        [0, s, 0.5 * s - face.margin_m[1]], [0, 0, 1]])
            board_to_pixel = intr.matrix() @ color_from_board[:3, [0, 1, 3]]
            pixel_to_super = np.array([[k, 0, (k - 1) / 2 - k * x0],
                                       [0, k, (k - 1) / 2 - k * y0], [0, 0, 1]])
            homography = pixel_to_super @ board_to_pixel @ source_to_board
            size = ((x1 - x0 + 1) * k, (y1 - y0 + 1) * k)
            warped = cv2.warpPerspective(face.image.astype(np.float32), homography, size,
                                         flags=cv2.INTER_CUBIC, borderValue=0.0)
            cover = cv2.warpPerspective(np.ones(face.image.shape, np.float32), homography, size,
                                        flags=cv2.INTER_CUBIC, borderValue=0.0)
            box = (x1 - x0 + 1, y1 - y0 + 1)
            warped = cv2.resize(warped, box, interpolation=cv2.INTER_AREA)
            cover = np.clip(cv2.resize(cover, box, interpolation=cv2.INTER_AREA), 0.0, 1.0)
            normal_world = -world_from_board[:3, 2]
            light = float(np.clip(lambert_shading(normal_world[None])[0], 0.35, 1.1))
            printed = (_INK + (_PAPER - _INK) * warped / 255.0) * light
            region = image[y0:y1 + 1, x0:x1 + 1]
            region[:] = cover * printed + (1.0 - cover) * region
        if self.maps is not None:
            # Bicubic: bilinear resampling blurs by sub-pixel phase, which biases corners.
            image = np.asarray(cv2.remap(image, self.maps[0], self.maps[1], cv2.INTER_CUBIC,
                                         borderMode=cv2.BORDER_REPLICATE), np.float32)
        if self.config.blur_sigma_px > 0:
            image = np.asarray(cv2.GaussianBlur(image, (0, 0), self.config.blur_sigma_px),
                               np.float32)
        image = image + rng.normal(0.0, self.config.color_noise_sigma, image.shape)
        gray = np.clip(np.rint(image), 0, 255).astype(np.uint8)
        return np.repeat(gray[:, :, None], 3, axis=2)


def synthesize_calibration(config: TargetSynthConfig,
                           cameras: Sequence[CameraInfo] | None = None,
                           progress: Callable[[float], None] | None = None
                           ) -> tuple[CaptureMeta, Iterator[View], dict[str, Matrix]]:
    """A calibration capture of a moving ChArUco target.

    cameras: the rig with TRUE ``world_from_depth`` (default: the synthetic 8-camera rig);
    cameras without colour get an Azure Kinect-like colour camera. Returns (meta with
    ``world_from_depth`` null and the target described, views rendered lazily frame by frame,
    the true ``world_from_depth`` per camera id).
    """
    if cameras is None:
        cameras = rig_cameras(RigConfig(camera_count=config.camera_count))
    rigged = [with_kinect_color(c, config) for c in cameras]
    truth = {}
    for camera in rigged:
        if camera.world_from_depth is None:
            raise ValueError(f"camera {camera.id!r}: needs its true world_from_depth")
        truth[camera.id] = np.asarray(camera.world_from_depth, dtype=float)
    target, margins = make_target(config)
    faces = _faces(target, margins)
    motion_rng, noise_rng = np.random.default_rng(config.seed).spawn(2)
    poses = target_trajectory(config, look_at_centre(list(truth.values())),
                              [pose[:3, 3] for pose in truth.values()], motion_rng)
    written = tuple(replace(c, world_from_depth=None) for c in rigged)
    meta = CaptureMeta(depth_scale=0.001, cameras=written,
                       frames=tuple(FrameInfo(index=i, timestamp_us=i * 33_333)
                                    for i in range(config.frame_count)),
                       target=target)
    biases = [draw_depth_bias_m(config.noise_model, noise_rng) for _ in rigged]

    def views() -> Iterator[View]:
        maps_cache: dict[Intrinsics, tuple[NDArray[np.float32], NDArray[np.float32]]] = {}
        renderers = [_ColorRenderer(c, truth[c.id], config, maps_cache) for c in rigged]
        for frame, pose in enumerate(poses):
            caster = MeshRaycaster(_plates_mesh(faces, pose))
            for index, camera in enumerate(written):
                rendering = caster.render(camera.depth_intrinsics, truth[camera.id])
                depth = rendering.depth_m
                if config.depth_noise:
                    depth = apply_kinect_noise(depth, rendering.normals_cam,
                                               camera.depth_intrinsics, config.noise_model,
                                               noise_rng, biases[index])
                color = renderers[index].render(faces, pose, noise_rng)
                yield View(camera=camera, frame_index=frame, depth_m=depth, color_rgb=color)
            if progress is not None:
                progress((frame + 1) / len(poses))

    return meta, views(), truth


def look_at_centre(world_from_depth: Sequence[Matrix]) -> Matrix:
    """The point nearest to every camera's optical axis (least squares), metres."""
    lhs, rhs = np.zeros((3, 3)), np.zeros(3)
    for pose in world_from_depth:
        axis = pose[:3, 2] / np.linalg.norm(pose[:3, 2])
        projector = np.eye(3) - np.outer(axis, axis)
        lhs += projector
        rhs += projector @ pose[:3, 3]
    if np.linalg.matrix_rank(lhs) < 3:
        return np.asarray(np.mean([p[:3, 3] + p[:3, 2] for p in world_from_depth], axis=0),
                          np.float64)
    return np.asarray(np.linalg.solve(lhs, rhs), np.float64)
