"""The reconstruction pipeline as named stages, run in-process or one by one by workers.

Stages pass artifacts: dicts of numpy arrays (workers store them as .npz). A stage's
``inputs`` are the artifacts of the stages before it, merged in order (later keys win);
every stage reads only the keys it documents. The mesh-producing stages all write
``vertices_m`` and ``faces``, so the merged artifacts always hold the latest mesh.

Stages (in order):
  filter    depth_m_<k> (H, W) float32: range limits, flying pixels, bilateral filter
  align     depth_m_<k> corrected by per-camera range offsets; depth_offset_m (C,);
            world_from_depth (C, 4, 4) touched-up poses (later stages use them); only
            corrections within the sensor's error budget that held-out overlaps show
  register  points_world (N, 3), normals_world (N, 3), camera_index (N,), point_colors;
            cropped to the rig's inner cylinder, without the floor
  refine    the same keys, only the points of each voxel's chosen camera
  mesh      vertices_m (V, 3), faces (F, 3): Poisson-disk samples, screened Poisson
  remesh    vertices_m, faces: isotropic remeshing with angle criteria
  fit       vertices_m, faces: the vertices moved along their normals onto the refined
            points' local planes, edges the points show bending split
  enhance   vertices_m moved to the enhanced depth views (only when ``enhance`` is set)
  colorize  vertices_m, faces, vertex_normals, vertex_colors (when the capture has colour)
Each stage may also write ``stats_<stage>``: a 0-d string array holding JSON figures.
"""

from __future__ import annotations

import dataclasses
import resource
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import CameraInfo, CaptureMeta
from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.reconstruct.align import (
    DepthView,
    align_report,
    apply_offsets,
    estimate_corrections,
)
from pipeline.reconstruct.colorize import ColorView, colorize_mesh
from pipeline.reconstruct.crop import crop_mask
from pipeline.reconstruct.depth_filter import filter_depth
from pipeline.reconstruct.meshing import mesh_cloud
from pipeline.reconstruct.registration import ray_image, register_view
from pipeline.reconstruct.remesh.isotropic import remesh
from pipeline.reconstruct.surface_fit import fit_to_cloud
from pipeline.reconstruct.voxel_refine import refine_mask
from pipeline.stage_artifacts import (
    Artifacts,
    CaptureReader,
    NetworksSource,
    Progress,
    mesh_from_artifacts,
    require_keys,
    stage_stats,
    stats_artifact,
    tick,
)
from pipeline.stage_config import ReconstructConfig, config_hash
from pipeline.stage_enhance import stage_enhance

STAGES: tuple[str, ...] = ("filter", "align", "register", "refine", "mesh", "remesh", "fit",
                           "enhance", "colorize")
ENHANCE_STAGE = "enhance"
SECTION_FIRST_STAGE: dict[str, str] = {
    "depth_filter": "filter", "align": "align", "registration": "register",
    "crop": "register", "voxel_refine": "refine", "meshing": "mesh", "remesh": "remesh",
    "surface_fit": "fit", "enhance": "enhance", "enhancement": "enhance", "colorize": "colorize"}
"""The first stage that reads each `ReconstructConfig` field. A field missing here counts as
read by every stage (stored outputs are then reused less, never wrongly); one whose reader is
not planned, by none."""


# ----------------------------------------------------------------------------- helpers

def posed_cameras(meta: CaptureMeta, config: ReconstructConfig) -> list[CameraInfo]:
    """The capture's cameras with their poses (overridden from the config); all needed."""
    overrides = {cid: np.asarray(values).reshape(4, 4) for cid, values in config.world_from_depth}
    unknown = set(overrides) - set(meta.camera_ids)
    if unknown:
        raise ValueError(f"world_from_depth: no camera {sorted(unknown)[0]!r} in the capture")
    cameras = []
    for cam in meta.cameras:
        pose = overrides.get(cam.id, cam.world_from_depth)
        if pose is None:
            raise ValueError(f"capture.json: cameras[{cam.id}].world_from_depth is null; "
                             "calibrate the rig and pass its rig.json")
        cameras.append(dataclasses.replace(cam, world_from_depth=np.asarray(pose, float)))
    return cameras


def _cameras(capture: CaptureReader, config: ReconstructConfig,
             inputs: Mapping[str, NDArray[Any]] | None = None) -> list[CameraInfo]:
    """The posed cameras; with the align stage's corrected poses when inputs hold them."""
    cameras = posed_cameras(capture.meta, config)
    aligned = None if inputs is None else inputs.get("world_from_depth")
    if aligned is None:
        return cameras
    if np.shape(aligned) != (len(cameras), 4, 4):
        raise ValueError("inputs: world_from_depth must hold one 4x4 pose per camera")
    return [dataclasses.replace(c, world_from_depth=np.asarray(p, dtype=np.float64))
            for c, p in zip(cameras, aligned, strict=True)]


def _frame(capture: CaptureReader, config: ReconstructConfig) -> int:
    frames = capture.meta.frame_indices
    if config.frame_index is None:
        return frames[0]
    if config.frame_index not in frames:
        raise ValueError(f"frame_index: the capture has no frame {config.frame_index} "
                         f"(frames: {frames[0]}..{frames[-1]})")
    return config.frame_index


def check_capture(capture: CaptureReader, config: ReconstructConfig) -> None:
    """Raise ValueError now if the capture cannot be reconstructed with this config (poses,
    frame), before any stage runs."""
    posed_cameras(capture.meta, config)
    _frame(capture, config)


def _depths(inputs: Mapping[str, NDArray[Any]], cameras: list[CameraInfo]
            ) -> list[NDArray[np.float32]]:
    try:
        return [np.asarray(inputs[f"depth_m_{k}"], dtype=np.float32)
                for k in range(len(cameras))]
    except KeyError as exc:
        raise ValueError(f"inputs: missing artifact {exc.args[0]} (run the filter stage)") \
            from None


# ----------------------------------------------------------------------------- stages

def _stage_filter(capture: CaptureReader, inputs: Mapping[str, NDArray[Any]],
                  config: ReconstructConfig, progress: Progress | None) -> Artifacts:
    cameras = _cameras(capture, config)
    frame = _frame(capture, config)
    out: Artifacts = {}
    valid = 0
    for k, cam in enumerate(cameras):
        view = capture.read_view(cam.id, frame, with_color=False)
        depth = filter_depth(view.depth_m, cam.depth_intrinsics.fx, config.depth_filter)
        out[f"depth_m_{k}"] = depth
        valid += int(np.count_nonzero(depth))
        tick(progress, (k + 1) / len(cameras))
    return out | stats_artifact("filter", {"frame_index": frame, "valid_pixels": valid})


def _stage_align(capture: CaptureReader, inputs: Mapping[str, NDArray[Any]],
                 config: ReconstructConfig, progress: Progress | None) -> Artifacts:
    cameras = _cameras(capture, config)
    depths = _depths(inputs, cameras)
    views = [DepthView(d, cam.depth_intrinsics, np.asarray(cam.world_from_depth))
             for d, cam in zip(depths, cameras, strict=True)]
    found = estimate_corrections(views, config.align)
    tick(progress, 0.8)
    out: Artifacts = {"depth_offset_m": found.offsets_m,
                      "world_from_depth": found.world_from_depth}
    for k, (depth, cam) in enumerate(zip(depths, cameras, strict=True)):
        out[f"depth_m_{k}"] = apply_offsets(depth, ray_image(cam.depth_intrinsics),
                                            found.offsets_m[k])
    poses = np.array([np.asarray(cam.world_from_depth) for cam in cameras])
    return out | stats_artifact("align", align_report([c.id for c in cameras], poses, found,
                                                      config.align))


def _stage_register(capture: CaptureReader, inputs: Mapping[str, NDArray[Any]],
                    config: ReconstructConfig, progress: Progress | None) -> Artifacts:
    cameras = _cameras(capture, config, inputs)
    depths = _depths(inputs, cameras)
    frame = _frame(capture, config)
    points, normals, index, colors = [], [], [], []
    all_colored = True
    for k, (depth, cam) in enumerate(zip(depths, cameras, strict=True)):
        color = None
        if cam.color_intrinsics is None:
            color = capture.read_view(cam.id, frame, with_color=True).color_rgb
        all_colored &= color is not None
        pts = register_view(depth, cam.depth_intrinsics, np.asarray(cam.world_from_depth),
                            color, config.registration)
        points.append(pts.points_world)
        normals.append(pts.normals_world)
        index.append(np.full(len(pts.points_world), k, dtype=np.int32))
        if pts.colors is not None:
            colors.append(pts.colors)
        tick(progress, (k + 1) / len(cameras))
    points_world = np.vstack(points)
    normals_world = np.vstack(normals).astype(np.float32)
    poses = [np.asarray(c.world_from_depth, dtype=np.float64) for c in cameras]
    footprints = [float(np.median(d[d > 0])) / c.depth_intrinsics.fx
                  for d, c in zip(depths, cameras, strict=True) if np.any(d > 0)]
    spacing = float(np.median(footprints)) if footprints else 0.0
    keep, floor_y = crop_mask(points_world, normals_world, poses, spacing, config.crop)
    out: Artifacts = {"points_world": points_world[keep], "normals_world": normals_world[keep],
                      "camera_index": np.concatenate(index)[keep]}
    if all_colored:
        out["point_colors"] = np.vstack(colors).astype(np.uint8)[keep]
    return out | stats_artifact("register", {"points": int(keep.sum()),
                                     "cropped_points": int((~keep).sum()),
                                     "floor_y_m": floor_y})


def _stage_refine(capture: CaptureReader, inputs: Mapping[str, NDArray[Any]],
                  config: ReconstructConfig, progress: Progress | None) -> Artifacts:
    cameras = _cameras(capture, config, inputs)
    points, normals, index = require_keys(inputs, ("points_world", "normals_world",
                                               "camera_index"), "refine")
    centres = np.array([np.asarray(c.world_from_depth)[:3, 3] for c in cameras])
    keep = refine_mask(np.asarray(points, dtype=np.float64), index.astype(np.int64), centres,
                       config.voxel_refine)
    out: Artifacts = {"points_world": points[keep], "normals_world": normals[keep],
                      "camera_index": index[keep]}
    if "point_colors" in inputs:
        out["point_colors"] = inputs["point_colors"][keep]
    tick(progress, 1.0)
    return out | stats_artifact("refine", {"points": int(keep.sum())})


def _stage_mesh(capture: CaptureReader, inputs: Mapping[str, NDArray[Any]],
                config: ReconstructConfig, progress: Progress | None) -> Artifacts:
    points, normals = require_keys(inputs, ("points_world", "normals_world"), "mesh")
    mesh, samples = mesh_cloud(np.asarray(points, dtype=np.float64),
                               np.asarray(normals, dtype=np.float32), config.meshing)
    tick(progress, 1.0)
    out: Artifacts = {"vertices_m": mesh.vertices_m, "faces": mesh.faces}
    return out | stats_artifact("mesh", {"samples": samples, "triangles": mesh.face_count})


def _stage_remesh(capture: CaptureReader, inputs: Mapping[str, NDArray[Any]],
                  config: ReconstructConfig, progress: Progress | None) -> Artifacts:
    mesh = mesh_from_artifacts(inputs)
    out, stats = remesh(mesh, config.remesh)
    tick(progress, 1.0)
    stats["triangles"] = out.face_count
    result: Artifacts = {"vertices_m": out.vertices_m, "faces": out.faces}
    return result | stats_artifact("remesh", stats)


def _stage_fit(capture: CaptureReader, inputs: Mapping[str, NDArray[Any]],
               config: ReconstructConfig, progress: Progress | None) -> Artifacts:
    points, normals = require_keys(inputs, ("points_world", "normals_world"), "fit")
    mesh = mesh_from_artifacts(inputs)
    fitted, split = fit_to_cloud(mesh, np.asarray(points, dtype=np.float64), normals,
                                 config.surface_fit)
    tick(progress, 1.0)
    moved_m = np.linalg.norm(fitted.vertices_m[:mesh.vertex_count] - mesh.vertices_m, axis=1)
    stats = {"moved_mean_m": float(moved_m.mean()) if len(moved_m) else 0.0,
             "split_edges": split, "triangles": fitted.face_count}
    out: Artifacts = {"vertices_m": fitted.vertices_m, "faces": fitted.faces}
    return out | stats_artifact("fit", stats)


def _stage_colorize(capture: CaptureReader, inputs: Mapping[str, NDArray[Any]],
                    config: ReconstructConfig, progress: Progress | None) -> Artifacts:
    mesh = mesh_from_artifacts(inputs)
    normals = vertex_normals(mesh.vertices_m, mesh.faces)
    out: Artifacts = {"vertices_m": mesh.vertices_m, "faces": mesh.faces,
                      "vertex_normals": normals}
    frame = _frame(capture, config)
    views = []
    for cam in _cameras(capture, config, inputs):
        view = capture.read_view(cam.id, frame, with_color=True)
        if view.color_rgb is not None:
            views.append(ColorView.from_view(dataclasses.replace(view, camera=cam)))
    if views:
        colored = colorize_mesh(dataclasses.replace(mesh, vertex_normals=normals), views,
                                config.colorize, progress)
        assert colored.vertex_colors is not None
        out["vertex_colors"] = colored.vertex_colors
    tick(progress, 1.0)
    return out | stats_artifact("colorize", {"color_views": len(views)})


_STAGE_FUNCTIONS = {"filter": _stage_filter, "align": _stage_align,
                    "register": _stage_register, "refine": _stage_refine,
                    "mesh": _stage_mesh, "remesh": _stage_remesh, "fit": _stage_fit,
                    "enhance": stage_enhance, "colorize": _stage_colorize}


def run_stage(name: str, capture: CaptureReader, inputs: Mapping[str, NDArray[Any]],
              config: ReconstructConfig, progress: Progress | None = None,
              networks: NetworksSource | None = None) -> Artifacts:
    """Run one stage on the merged artifacts of the stages before it; returns its artifacts.
    `networks`: gives the enhance stage's, kept between jobs (`pipeline.enhance.networks`),
    asked for only where the mesh is enhanced (None: the stage loads them)."""
    if name not in _STAGE_FUNCTIONS:
        raise ValueError(f"stage: unknown stage {name!r} (stages: {', '.join(STAGES)})")
    if name == ENHANCE_STAGE:
        return stage_enhance(capture, inputs, config, progress, networks)
    return _STAGE_FUNCTIONS[name](capture, inputs, config, progress)


def planned_stages(config: ReconstructConfig) -> tuple[str, ...]:
    """The stages a reconstruction with this config runs (enhance only when asked)."""
    return tuple(s for s in STAGES if config.enhance or s != ENHANCE_STAGE)


def reconstruct(capture: CaptureReader, config: ReconstructConfig,
                progress: Progress | None = None,
                on_stage: Callable[[str], None] | None = None
                ) -> tuple[TriangleMesh, dict[str, Any]]:
    """All stages in-process: the mesh and a report (stage wall times and figures).

    ``progress`` gets the overall fraction done; ``on_stage`` the name of each stage as it
    starts.
    """
    check_capture(capture, config)
    stages = planned_stages(config)
    artifacts: Artifacts = {}
    seconds: dict[str, float] = {}
    cpu_seconds: dict[str, float] = {}
    for index, name in enumerate(stages):
        if on_stage is not None:
            on_stage(name)

        def stage_progress(fraction: float, index: int = index) -> None:
            tick(progress, (index + fraction) / len(stages))

        started, cpu_started = time.perf_counter(), _cpu_seconds()
        artifacts.update(run_stage(name, capture, artifacts, config, stage_progress))
        seconds[name] = round(time.perf_counter() - started, 3)
        cpu_seconds[name] = round(_cpu_seconds() - cpu_started, 3)
        _drop_consumed(artifacts, name)
    mesh = mesh_from_artifacts(artifacts)
    stats = stage_stats(artifacts)
    report = {"stages": list(stages), "stage_seconds": seconds,
              "total_seconds": round(sum(seconds.values()), 3),
              "stage_cpu_seconds": cpu_seconds,
              "points": stats.get("register", {}).get("points"),
              "refined_points": stats.get("refine", {}).get("points"),
              "samples": stats.get("mesh", {}).get("samples"),
              "vertices": mesh.vertex_count, "triangles": mesh.face_count,
              "enhance": {"requested": config.enhance, "applied": ENHANCE_STAGE in stages},
              "stage_stats": stats, "config_hash": config_hash(config)}
    return mesh, report


def _cpu_seconds() -> float:
    """CPU time of this process and its finished children (the remesh kernel runs in one)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def _drop_consumed(artifacts: Artifacts, stage: str) -> None:
    """Free what no later stage reads (the in-process run keeps memory low)."""
    if stage == "register":
        for key in [k for k in artifacts if k.startswith("depth_m_")]:
            del artifacts[key]
    if stage == "fit":
        for key in ("points_world", "normals_world", "camera_index", "point_colors"):
            artifacts.pop(key, None)
