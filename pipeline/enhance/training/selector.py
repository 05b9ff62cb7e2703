"""Training the twicing selector: noisy meshes with known truth, and a loss that is the
blend's squared distance to the truth."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import NDArray

from pipeline.enhance.inference import selector_blend
from pipeline.enhance.metrics import signed_c2m
from pipeline.enhance.models.twicing_selector import SelectorConfig, TwicingSelector
from pipeline.enhance.presmooth.scale_selection import twicing_candidates
from pipeline.enhance.training.data import (
    NOISE_KINDS,
    NoiseKind,
    isotropic,
    noise_kind,
    noisy_along_normals,
    unit_extent,
)
from pipeline.enhance.training.row_fit import fit_rows
from pipeline.geometry.mesh import TriangleMesh
from pipeline.geometry.smoothing import AdaptiveTwicingConfig, adaptive_twicing


@dataclass(frozen=True)
class SelectorTrainConfig:
    """Data and budget of the selector stage."""

    model: SelectorConfig = SelectorConfig()
    draws_per_mesh: int = 2
    """Noisy copies (remesh and noise drawn afresh) of each source mesh."""
    edge_fraction: tuple[float, float] = (0.004, 0.007)
    """Range of the remesh's edge length, fraction of the mesh's largest extent."""
    noise_to_edge: tuple[float, float] = (0.3, 2.5)
    """Range of the noise amplitude along normals (the bound of uniform noise; the other kinds
    have its standard deviation), in edge lengths (the benchmark's protocol: 10 mm on 5 mm
    edges, 2)."""
    noise_kinds: tuple[NoiseKind, ...] = NOISE_KINDS
    """Noise models each draw's noise is drawn from, one per draw at random."""
    vertices_per_draw: int = 40_000
    """Vertices of each draw kept for training (drawn at random; large meshes would dominate)."""
    steps: int = 3000
    minutes: float = 10.0
    batch: int = 4096
    lr: float = 1e-3


@dataclass(frozen=True)
class SelectorExample:
    """One noisy draw of a mesh: the selector's input and each candidate's error."""

    name: str
    features: NDArray[np.float32]
    """(V, F) `twicing_candidates` features."""
    errors: NDArray[np.float32]
    """(V, K) signed distance of each candidate's vertex to the truth, in noise stds."""
    noise_std_m: float


def selector_examples(
    meshes: Sequence[tuple[str, TriangleMesh]],
    config: SelectorTrainConfig,
    rng: np.random.Generator,
    progress: Callable[[float], None] | None = None,
) -> list[SelectorExample]:
    """`draws_per_mesh` noisy draws of each mesh (scaled to unit extent and remeshed as the
    enhance stage receives meshes), each cut to at most `vertices_per_draw` random vertices."""
    out = []
    total = len(meshes) * config.draws_per_mesh
    for name, mesh in meshes:
        unit = unit_extent(mesh, name)
        for _ in range(config.draws_per_mesh):
            truth, noisy = noisy_draw(unit, config.edge_fraction, config.noise_to_edge, rng,
                                      config.noise_kinds)
            cand = twicing_candidates(noisy, config.model.blend)
            errors = np.stack([signed_c2m(v, truth) for v in cand.vertices_m], axis=1)
            keep = np.arange(noisy.vertex_count)
            if len(keep) > config.vertices_per_draw:
                keep = rng.choice(len(keep), config.vertices_per_draw, replace=False)
            out.append(SelectorExample(name, cand.features[keep],
                                       (errors[keep] / cand.noise_std_m).astype(np.float32),
                                       cand.noise_std_m))
            if progress is not None:
                progress(len(out) / total)
    return out


def noisy_draw(
    unit: TriangleMesh, edge_fraction: tuple[float, float], noise_to_edge: tuple[float, float],
    rng: np.random.Generator, kinds: tuple[NoiseKind, ...],
) -> tuple[TriangleMesh, TriangleMesh]:
    """(truth, noisy): the unit-extent mesh remeshed at an edge drawn from `edge_fraction`,
    then noised along normals by an amplitude drawn from `noise_to_edge` edge lengths, with
    a noise model drawn from `kinds`."""
    edge = float(rng.uniform(*edge_fraction))
    truth = isotropic(unit, edge)
    amplitude = edge * float(rng.uniform(*noise_to_edge))
    return truth, noisy_along_normals(truth, amplitude, rng, noise_kind(kinds, rng))


def blend_loss(weights: torch.Tensor, errors: torch.Tensor) -> torch.Tensor:
    """Mean squared distance to the truth of the blended vertices, (B, K) each: a blend's
    signed distance is the weighted sum of its candidates' (the surface is flat at that scale)."""
    return ((weights * errors).sum(dim=1) ** 2).mean()


def train_selector(
    examples: Sequence[SelectorExample],
    config: SelectorTrainConfig,
    seed: int,
    progress: Callable[[float, str], None] | None = None,
) -> tuple[TwicingSelector, dict]:
    """The trained selector, and {steps, train_seconds, final_loss}."""
    torch.manual_seed(seed)
    features = torch.from_numpy(np.concatenate([e.features for e in examples]))
    errors = torch.from_numpy(np.concatenate([e.errors for e in examples]))
    model = TwicingSelector(config.model)
    model.set_normalisation(features)

    def batch_loss(i: torch.Tensor) -> torch.Tensor:
        return blend_loss(model(features[i]), errors[i])

    log = fit_rows(model, len(features), batch_loss, config.steps, config.minutes, config.batch,
                   config.lr, seed, progress, "selector")
    return model, log


def validate_selector(
    model: TwicingSelector, meshes: Sequence[tuple[str, TriangleMesh]],
    config: SelectorTrainConfig, rng: np.random.Generator,
) -> dict[str, dict[str, float]]:
    """Per held-out mesh (one draw each), RMS distance to the truth in permille of the extent
    of: the noisy mesh, the best single candidate count, adaptive twicing, the selector's blend."""
    out = {}
    for name, mesh in meshes:
        truth, noisy = noisy_draw(unit_extent(mesh, name), config.edge_fraction,
                                  config.noise_to_edge, rng, config.noise_kinds)
        cand = twicing_candidates(noisy, config.model.blend)
        blended = selector_blend(model, cand)
        adaptive = adaptive_twicing(noisy, AdaptiveTwicingConfig(passes=config.model.passes))

        def rms(v: NDArray[np.float64], truth: TriangleMesh = truth) -> float:
            return float(np.sqrt(np.mean(signed_c2m(v, truth) ** 2)) * 1e3)

        out[name] = {
            "noisy": rms(noisy.vertices_m),
            "best_count": min(rms(v) for v in cand.vertices_m),
            "adaptive_twicing": rms(adaptive.vertices_m),
            "selector": rms(blended),
        }
    return out
