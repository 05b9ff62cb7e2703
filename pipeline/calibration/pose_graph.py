"""Initial poses: chain camera pairs that saw the target together into one pose graph.

The graph's nodes are the cameras and the target poses (one per frame); a view is an edge.
Cameras are joined along a maximum spanning tree of "frames seen together", each tree edge's
relative pose being a robust average over those frames, so a single bad PnP cannot spoil it.
The world frame here is the reference camera's colour frame.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from pipeline.calibration.transforms import invert, robust_average_poses

ViewKey = tuple[str, int]
Matrix = NDArray[np.float64]


def _frames_by_camera(view_poses: Mapping[ViewKey, Matrix]) -> dict[str, dict[int, Matrix]]:
    out: dict[str, dict[int, Matrix]] = defaultdict(dict)
    for (camera_id, frame), pose in view_poses.items():
        out[camera_id][frame] = pose
    return out


def shared_frames(view_poses: Mapping[ViewKey, Matrix]) -> dict[tuple[str, str], list[int]]:
    """For each camera pair (a < b), the frames in which both saw the target."""
    cameras_of_frame: dict[int, list[str]] = defaultdict(list)
    for camera_id, frame in view_poses:
        cameras_of_frame[frame].append(camera_id)
    pairs: dict[tuple[str, str], list[int]] = defaultdict(list)
    for frame, cameras in cameras_of_frame.items():
        ordered = sorted(cameras)
        for i, a in enumerate(ordered):
            for b in ordered[i + 1:]:
                pairs[(a, b)].append(frame)
    return dict(pairs)


def _spanning_tree(reference: str, pairs: Mapping[tuple[str, str], list[int]]
                   ) -> list[tuple[str, str]]:
    """(parent, child) edges of a maximum spanning tree by shared frame count (Prim)."""
    reached = {reference}
    edges: list[tuple[str, str]] = []
    while True:
        best: tuple[int, str, str] | None = None
        for (a, b), frames in sorted(pairs.items()):
            if (a in reached) == (b in reached):
                continue
            parent, child = (a, b) if a in reached else (b, a)
            if best is None or len(frames) > best[0]:
                best = (len(frames), parent, child)
        if best is None:
            return edges
        edges.append((best[1], best[2]))
        reached.add(best[2])


def initial_poses(view_poses: Mapping[ViewKey, Matrix], camera_ids: Sequence[str],
                  reference: str) -> tuple[dict[str, Matrix], dict[int, Matrix]]:
    """``world_from_color`` per camera and ``world_from_target`` per frame.

    view_poses: ``color_from_target`` of every usable view. Only frames seen by two or more
    cameras get a target pose (a frame seen once constrains no camera). Raises ValueError
    naming the cameras that saw no target, or that the graph cannot join to the reference.
    """
    by_camera = _frames_by_camera(view_poses)
    blind = [c for c in camera_ids if c not in by_camera]
    if blind:
        raise ValueError(f"calibration: camera(s) {', '.join(blind)} saw no usable view of the "
                         "target; move the target where they can see it")
    pairs = shared_frames(view_poses)
    if not pairs:
        raise ValueError("calibration: no frame shows the target to two cameras at once; "
                         "cameras cannot be related")
    edges = _spanning_tree(reference, pairs)
    joined = {reference} | {child for _, child in edges}
    apart = [c for c in camera_ids if c not in joined]
    if apart:
        raise ValueError(f"calibration: the camera graph is disconnected: camera(s) "
                         f"{', '.join(apart)} share no target frame with "
                         f"{', '.join(sorted(joined))}")
    world_from_color = {reference: np.eye(4)}
    for parent, child in edges:
        frames = pairs[(parent, child) if parent < child else (child, parent)]
        relative = robust_average_poses(
            [by_camera[parent][f] @ invert(by_camera[child][f]) for f in frames],
            angle_deg=3.0, distance_m=0.1)
        world_from_color[child] = world_from_color[parent] @ relative
    return world_from_color, target_poses(view_poses, world_from_color)


def target_poses(view_poses: Mapping[ViewKey, Matrix], world_from_color: Mapping[str, Matrix]
                 ) -> dict[int, Matrix]:
    """Robust ``world_from_target`` of every frame two or more posed cameras saw."""
    guesses: dict[int, list[Matrix]] = defaultdict(list)
    for (camera_id, frame), pose in view_poses.items():
        if camera_id in world_from_color:
            guesses[frame].append(world_from_color[camera_id] @ pose)
    return {frame: robust_average_poses(poses, angle_deg=3.0, distance_m=0.1)
            for frame, poses in sorted(guesses.items()) if len(poses) >= 2}
