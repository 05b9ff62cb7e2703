"""Training pairs: clean depth renders and the same views degraded as reconstruction degrades them.

Source meshes are first remeshed isotropically by the pipeline's own remesh stage, because
that is what the enhance stage receives. Degradations: vertex noise along normals (the
benchmark's), Azure-Kinect-like axial depth noise with flying pixels at edges, holes, and 4x
down-then-up sampling. Everything is in normalised depth (`render/`), so the scale of a source
mesh does not matter.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.render.views import canny_edges, make_views, render_depth
from pipeline.geometry.mesh import TriangleMesh, vertex_normals

NoiseKind = Literal["uniform", "gaussian", "laplace"]
NOISE_KINDS: tuple[NoiseKind, ...] = ("uniform", "gaussian", "laplace")
"""The noise models of `noisy_along_normals`: the paper's protocol's, and two as sensors make it
(per-pixel Gaussian noise; heavy tails from flying pixels and multipath)."""


@dataclass(frozen=True)
class DataConfig:
    """How many pairs to make and how to degrade them."""

    resolution: int = 256
    """Render side in pixels."""
    poses_per_mesh: int = 8
    """Random rotations (each with its own noise draw) per source mesh."""
    views_per_pose: int = 6
    """Random viewing directions per pose."""
    edge_fraction: tuple[float, float] = (0.004, 0.007)
    """Range of the isotropic remesh's edge length, fraction of the mesh's largest extent."""
    noise_fraction: tuple[float, float] = (0.004, 0.013)
    """Range of the uniform vertex-noise amplitude along normals, fraction of largest extent."""
    light_noise_probability: float = 0.25
    """Chance a pose's noise amplitude is drawn from [0, noise_fraction[0]) instead: near-clean
    surfaces, as a good reconstruction or an already enhanced mesh is. Networks trained only on
    heavy noise remove that noise's first-hit bias from every surface and push clean ones
    inwards."""
    kinect_probability: float = 0.25
    """Chance a view also gets Azure-Kinect-like axial noise and flying pixels."""
    hole_probability: float = 0.2
    """Chance a view gets holes punched in it."""
    downup_probability: float = 0.2
    """Chance a view is 4x downsampled and bilinearly upsampled."""
    noise_kinds: tuple[NoiseKind, ...] = NOISE_KINDS
    """Noise models a pose's vertex noise is drawn from (`noisy_along_normals`), one per pose at
    random: no stage may rest on one noise model."""
    color_probability: float = 0.5
    """Chance a pose's mesh gets synthetic colour (`synthetic_colors`), whose Canny edges the
    networks then read as at inference on a coloured mesh; the other poses have none (edges
    zero), as an uncoloured mesh has."""


MIXES: dict[str, dict[str, Any]] = {
    "full": {},
    "mesh": {"kinect_probability": 0.0, "hole_probability": 0.0, "downup_probability": 0.0},
}
"""Degradation mixes by name. `full`: every degradation of a depth sensor. `mesh`: only what a
mesh's renders carry (vertex noise along normals, near-clean surfaces, colour), the input of
the enhance stage, which renders a mesh: sensor noise, holes and resampling never reach it.
The shipped depth networks are trained on `mesh` with the tight loss mask (MODEL_CARD.md)."""


def with_mix(config: DataConfig, mix: str) -> DataConfig:
    """`config` with the degradation mix named `mix` (`MIXES`) applied."""
    if mix not in MIXES:
        raise ValueError(f"mix: {mix!r} is not one of {', '.join(MIXES)}")
    return replace(config, **MIXES[mix])


@dataclass(frozen=True)
class DepthPairs:
    """Aligned degraded/clean normalised depth images."""

    degraded_n: NDArray[np.float32]
    """(N, H, W) the base depth the networks correct: the degraded render of the pre-smoothed
    noisy mesh, normalised (1 where invalid)."""
    degraded_valid: NDArray[np.bool_]
    """(N, H, W) validity of the base depth."""
    noisy_n: NDArray[np.float32]
    """(N, H, W) the degraded render of the noisy mesh itself (1 where invalid)."""
    clean_n: NDArray[np.float32]
    """(N, H, W) clean normalised depth of the same view."""
    loss_mask: NDArray[np.bool_]
    """(N, H, W) pixels valid in both images (where a loss is defined)."""
    edges: NDArray[np.bool_]
    """(N, H, W) Canny edges of the degraded view's colour render (all False without colour)."""
    source: tuple[str, ...]
    """(N,) name of the source mesh of each pair."""


def random_rotation(rng: np.random.Generator) -> NDArray[np.float64]:
    """A uniformly random 3x3 rotation (QR of a Gaussian matrix, sign-fixed)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def isotropic(mesh: TriangleMesh, edge_m: float) -> TriangleMesh:
    """The mesh remeshed to edges of about `edge_m` by the pipeline's remesh stage.

    Vertex noise on a midpoint-subdivided mesh (long thin triangles, uneven valence) folds the
    surface far more than on the pipeline's isotropic meshes, and networks trained on its
    renders over-correct. If the remesh kernel fails, midpoint subdivision stands in.
    """
    from pipeline.reconstruct.remesh.isotropic import RemeshConfig, remesh

    out, stats = remesh(mesh, RemeshConfig(target_edge_length_m=edge_m, iterations=6,
                                           min_component_share=0.0))
    if stats["warning"] is not None:
        return subdivide_to(mesh, edge_m)
    return out


def subdivide_to(mesh: TriangleMesh, edge_m: float, max_faces: int = 400_000) -> TriangleMesh:
    """Midpoint-subdivides until the mean edge is at most `edge_m` (or the face budget is hit)."""
    import open3d as o3d

    o3 = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices_m), o3d.utility.Vector3iVector(mesh.faces)
    )
    while True:
        v, f = np.asarray(o3.vertices), np.asarray(o3.triangles)
        mean_edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).mean()
        if mean_edge <= edge_m or len(f) * 4 > max_faces:
            break
        o3 = o3.subdivide_midpoint(1)
    return TriangleMesh(np.asarray(o3.vertices).copy(), np.asarray(o3.triangles).astype(np.int32))


PROCEDURAL = "procedural-"
"""Name prefix of the procedural shapes."""


def procedural_meshes(rng: np.random.Generator, count: int) -> list[tuple[str, TriangleMesh]]:
    """Spheres, tori, boxes, cylinders and lumpy blobs, at least ~1000 faces each."""
    import open3d as o3d

    out: list[tuple[str, TriangleMesh]] = []
    for i in range(count):
        kind = i % 5
        if kind == 0:
            m = o3d.geometry.TriangleMesh.create_sphere(1.0, 40)
        elif kind == 1:
            m = o3d.geometry.TriangleMesh.create_torus(1.0, rng.uniform(0.2, 0.5), 60, 30)
        elif kind == 2:
            m = o3d.geometry.TriangleMesh.create_box(*rng.uniform(0.4, 1.0, 3)).subdivide_midpoint(
                3
            )
        elif kind == 3:
            m = o3d.geometry.TriangleMesh.create_cylinder(rng.uniform(0.3, 0.6), 1.0, 40, 8)
        else:
            m = o3d.geometry.TriangleMesh.create_sphere(1.0, 60)
        m.remove_duplicated_vertices()
        v = np.asarray(m.vertices).copy()
        f = np.asarray(m.triangles).astype(np.int32)
        if kind == 4:  # lumpy blob: radial displacement by a few random low-frequency waves
            d = v / np.linalg.norm(v, axis=1, keepdims=True)
            bump = np.zeros(len(v))
            for _ in range(6):
                k = rng.normal(size=3) * rng.uniform(1.0, 4.0)
                bump += rng.uniform(0.03, 0.12) * np.sin(d @ k + rng.uniform(0, 2 * np.pi))
            v = d * (1.0 + bump)[:, None]
        v = v * rng.uniform(0.6, 1.4, 3)  # anisotropic stretch
        out.append((f"{PROCEDURAL}{i}", TriangleMesh(v, f)))
    return out


def synthetic_colors(mesh: TriangleMesh, rng: np.random.Generator) -> NDArray[np.uint8]:
    """(V, 3) sRGB vertex colours: a few flat albedo patches (texture edges that say nothing of
    the shape) shaded by the clean surface's normals under a random light (shading edges at
    creases, as a colour camera sees them, untouched by depth noise)."""
    v = mesh.vertices_m
    seeds = v[rng.choice(len(v), size=int(rng.integers(3, 12)), replace=False)]
    patch = np.argmin(((v[:, None, :] - seeds[None]) ** 2).sum(-1), axis=1)
    albedo = rng.uniform(0.2, 1.0, (len(seeds), 3))[patch]
    light = rng.normal(size=3)
    light /= np.linalg.norm(light)
    lambert = np.clip(vertex_normals(v, mesh.faces) @ light, 0.0, 1.0)
    shade = 0.35 + 0.65 * lambert
    return np.clip(albedo * shade[:, None] * 255.0, 0, 255).astype(np.uint8)


def _kinect_noise(depth: NDArray, valid: NDArray, range_m: float, rng: np.random.Generator):
    """Axial noise growing with depth (a 1 m model seen from ~1.5 m) plus flying edge pixels."""
    import cv2

    sigma_m = 0.0008 + 0.0012 * (1.0 + depth) ** 2  # Azure Kinect: ~1-3 mm over the range
    noise = rng.normal(size=depth.shape).astype(np.float32)
    noise = cv2.GaussianBlur(noise, (3, 3), 0.7) * 1.6  # a little spatial correlation
    out = depth + noise * sigma_m / range_m
    d = np.where(valid, depth, 1.0).astype(np.float32)
    jump = np.maximum(
        np.abs(cv2.Sobel(d, cv2.CV_32F, 1, 0)), np.abs(cv2.Sobel(d, cv2.CV_32F, 0, 1))
    )
    flying = valid & (jump > 0.05) & (rng.random(depth.shape) < 0.3)
    out[flying] += rng.uniform(-0.03, 0.03, int(flying.sum()))
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _holes(valid: NDArray, rng: np.random.Generator) -> NDArray:
    import cv2

    mask = np.zeros(valid.shape, np.uint8)
    h, w = valid.shape
    for _ in range(int(rng.integers(1, 5))):
        center = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        axes = (int(rng.integers(2, w // 16 + 3)), int(rng.integers(2, h // 16 + 3)))
        cv2.ellipse(mask, center, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    return valid & (mask == 0)


def _down_up(depth: NDArray, valid: NDArray) -> tuple[NDArray, NDArray]:
    import cv2

    h, w = depth.shape
    small = cv2.resize(
        np.where(valid, depth, 1.0), (w // 4, h // 4), interpolation=cv2.INTER_NEAREST
    )
    up = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    small_valid = cv2.resize(
        valid.astype(np.uint8), (w // 4, h // 4), interpolation=cv2.INTER_NEAREST
    )
    up_valid = cv2.resize(small_valid, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    return up.astype(np.float32), up_valid & valid


def noisy_along_normals(
    mesh: TriangleMesh, amplitude_m: float, rng: np.random.Generator,
    kind: NoiseKind = "uniform",
) -> TriangleMesh:
    """Every vertex moved along its normal by noise of `kind`: uniform in ±amplitude (the
    benchmark's), or Gaussian or Laplace of the same standard deviation (amplitude / √3)."""
    n = vertex_normals(mesh.vertices_m, mesh.faces).astype(np.float64)
    return mesh.with_vertices(mesh.vertices_m + n * normal_offsets_m(
        kind, amplitude_m, rng, mesh.vertex_count))


def normal_offsets_m(kind: NoiseKind, amplitude_m: float, rng: np.random.Generator,
                     count: int) -> NDArray[np.float64]:
    """(count, 1) offsets along the normals, metres: `noisy_along_normals`'s noise. The uniform
    draw is the one the protocol always made, so its seeded figures stay as they were."""
    std_m = amplitude_m / np.sqrt(3.0)  # the standard deviation of uniform noise in ±amplitude
    if kind == "uniform":
        return rng.uniform(-amplitude_m, amplitude_m, (count, 1))
    if kind == "gaussian":
        return rng.normal(0.0, std_m, (count, 1))
    if kind == "laplace":  # its scale b has standard deviation b√2
        return rng.laplace(0.0, std_m / np.sqrt(2.0), (count, 1))
    raise ValueError(f"noise kind {kind!r}: one of {', '.join(NOISE_KINDS)}")


def noise_kind(kinds: Sequence[NoiseKind], rng: np.random.Generator) -> NoiseKind:
    """One of `kinds` at random; a single kind without a draw, so its seeded data stay as
    they were."""
    if not kinds or any(k not in NOISE_KINDS for k in kinds):
        raise ValueError(f"noise kinds {tuple(kinds)}: one or more of {', '.join(NOISE_KINDS)}")
    return kinds[0] if len(kinds) == 1 else kinds[int(rng.integers(len(kinds)))]


def _noise_amplitude(config: DataConfig, rng: np.random.Generator) -> float:
    """A pose's vertex-noise amplitude, fraction of the largest extent."""
    if rng.random() < config.light_noise_probability:
        return float(rng.uniform(0.0, config.noise_fraction[0]))
    return float(rng.uniform(*config.noise_fraction))


def make_pairs(
    meshes: Sequence[tuple[str, TriangleMesh]],
    config: DataConfig,
    seed: int,
    progress: Callable[[float], None] | None = None,
) -> DepthPairs:
    """Renders `poses_per_mesh * views_per_pose` degraded/clean pairs of every named mesh."""
    if not meshes:
        raise ValueError("meshes: need at least one source mesh")
    rng = np.random.default_rng(seed)
    parts: list[DepthPairs] = []
    total = len(meshes) * config.poses_per_mesh
    for name, mesh in meshes:
        # Remeshing does not depend on the pose, so one remesh serves all of a mesh's poses.
        remeshed = isotropic(unit_extent(mesh, name), rng.uniform(*config.edge_fraction))
        for _ in range(config.poses_per_mesh):
            parts.append(pose_pairs(name, remeshed, config, rng))
            if progress is not None:
                progress(len(parts) / total)
    return concat_pairs(parts)


def unit_extent(mesh: TriangleMesh, name: str) -> TriangleMesh:
    """The mesh centred and scaled to a largest extent of 1."""
    extent = float(np.ptp(mesh.vertices_m, axis=0).max())
    if extent <= 0:
        raise ValueError(f"meshes[{name}]: degenerate mesh")
    return TriangleMesh((mesh.vertices_m - mesh.vertices_m.mean(axis=0)) / extent, mesh.faces)


def concat_pairs(parts: Sequence[DepthPairs]) -> DepthPairs:
    """The pairs of `parts`, in order, as one set."""
    def cat(field: str) -> NDArray:
        return np.concatenate([getattr(p, field) for p in parts])

    return DepthPairs(
        cat("degraded_n"), cat("degraded_valid"), cat("noisy_n"), cat("clean_n"),
        cat("loss_mask"), cat("edges"), tuple(n for p in parts for n in p.source),
    )


def pose_pairs(
    name: str, remeshed: TriangleMesh, config: DataConfig, rng: np.random.Generator
) -> DepthPairs:
    """The `views_per_pose` pairs of one random pose of a remeshed unit-extent mesh."""
    fine = remeshed.with_vertices(remeshed.vertices_m @ random_rotation(rng).T)
    if rng.random() < config.color_probability:
        fine = replace(fine, vertex_colors=synthetic_colors(fine, rng))
    noisy = noisy_along_normals(fine, _noise_amplitude(config, rng), rng,
                                noise_kind(config.noise_kinds, rng))
    forwards = rng.normal(size=(config.views_per_pose, 3))
    views = make_views(noisy.vertices_m, forwards, config.resolution)
    r_noisy = render_depth(noisy, views, with_color=True)
    r_base = render_depth(_presmoothed(noisy), views, with_color=False)
    r_clean = render_depth(fine, views, with_color=False)
    # Every degradation below only shrinks the valid mask, so the render's edges
    # masked by a view's final mask are that view's edges.
    pose_edges = canny_edges(r_noisy.color_rgb, r_noisy.valid)
    deg, deg_valid, noisy_out, mask, edges = [], [], [], [], []
    for k in range(views.count):
        d, v = r_noisy.depth_n[k].copy(), r_noisy.valid[k].copy()
        b, bv = r_base.depth_n[k].copy(), r_base.valid[k].copy()
        # Sensor noise marks the noisy surface; the smoothed one averages it away.
        if rng.random() < config.kinect_probability:
            d = _kinect_noise(d, v, views.depth_range_m, rng)
        if rng.random() < config.downup_probability:
            d, v = _down_up(d, v)
            b, bv = _down_up(b, bv)
        if rng.random() < config.hole_probability:
            holes = _holes(np.ones_like(v), rng)
            v, bv = v & holes, bv & holes
        noisy_out.append(np.where(v, d, 1.0).astype(np.float32))
        deg.append(np.where(bv, b, 1.0).astype(np.float32))
        deg_valid.append(bv)
        edges.append(np.zeros_like(bv) if pose_edges is None else bv & (pose_edges[k] > 0))
        mask.append(bv & r_clean.valid[k])
    return DepthPairs(
        np.stack(deg), np.stack(deg_valid), np.stack(noisy_out), r_clean.depth_n.copy(),
        np.stack(mask), np.stack(edges), (name,) * views.count,
    )


def _presmoothed(noisy: TriangleMesh) -> TriangleMesh:
    """The mesh whose render is the networks' base depth: pre-smoothed as the enhance stage
    does it, by the shipped selector and the midrange estimator."""
    from pipeline.enhance.inference import selector_presmoothed
    from pipeline.enhance.presmooth.midrange import BoundedNoiseConfig
    from pipeline.enhance.weights import shipped_bytes
    from pipeline.enhance.weights.loading import load_selector

    return selector_presmoothed(noisy, load_selector(shipped_bytes("selector")),
                                BoundedNoiseConfig())


SAME_SURFACE_N = 0.05
"""`same_surface_mask`'s default threshold (normalised depth): the validation scores' and
the default loss mask's."""
BULK_SURFACE_N = 0.02
"""A tighter threshold, the bulk of the surface. At `SAME_SURFACE_N` a few pixels still see
another surface in one input; they carry much of a squared loss while the mesh update, which
averages many views, barely feels them."""


def same_surface_mask(
    pairs: DepthPairs,
    idx: int | slice | NDArray[np.int64] = slice(None),
    threshold_n: float = SAME_SURFACE_N,
) -> NDArray[np.bool_]:
    """(n, H, W), or (H, W) for one index: loss-mask pixels where neither input is more than
    `threshold_n` (normalised depth) from the clean render, i.e. sees another surface than it
    (silhouettes, self-occlusion). No enhancer could recover them, and their few huge
    residuals would dominate a squared loss or a score."""
    clean = pairs.clean_n[idx]
    mask = pairs.loss_mask[idx] & (np.abs(clean - pairs.degraded_n[idx]) < threshold_n)
    noisy = pairs.noisy_n[idx]
    return mask & ((noisy >= 1.0) | (np.abs(clean - noisy) < threshold_n))
