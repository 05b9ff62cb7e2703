"""Training the vertex gain networks: noisy meshes with known truth, each network's view steps
on them, and a loss that is the moved vertex's squared distance to the truth."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from numpy.typing import NDArray

from pipeline.enhance.config import EnhanceConfig
from pipeline.enhance.device import resolve_device
from pipeline.enhance.enhancement import enhance_renders, update_inputs
from pipeline.enhance.inference import vertex_gains
from pipeline.enhance.metrics import signed_c2m
from pipeline.enhance.models.vertex_gain import VertexGainConfig, VertexGainNet
from pipeline.enhance.training.data import NOISE_KINDS, PROCEDURAL, NoiseKind, unit_extent
from pipeline.enhance.training.row_fit import fit_rows
from pipeline.enhance.training.selector import noisy_draw
from pipeline.enhance.update.steps import UpdateConfig, ViewSteps, apply_view_steps, view_steps
from pipeline.enhance.update.vertex_gain import MEAN_STEP, gain_features
from pipeline.geometry.mesh import TriangleMesh, mean_edge_length_m

FIXED_GAIN = 0.7
"""The one share of the correction for every vertex that the learned gains are validated
against: the best such share on the validation meshes."""


@dataclass(frozen=True)
class GainTrainConfig:
    """Data and budget of the gain stage (one network per method, on the same draws)."""

    model: VertexGainConfig = field(default_factory=VertexGainConfig)
    methods: tuple[str, ...] = ("ldm", "regressor")
    with_procedural: bool = False
    """Also train on the procedural shapes. Off: their flat faces and sharp edges teach the
    gains to trust corrections that organic surfaces do not bear out."""
    draws_per_mesh: int = 4
    """Noisy copies (remesh and noise drawn afresh) of each source mesh."""
    edge_fraction: tuple[float, float] = (0.004, 0.007)
    """Range of the remesh's edge length, fraction of the mesh's largest extent."""
    noise_to_edge: tuple[float, float] = (0.3, 2.5)
    """Range of the noise amplitude along normals (the bound of uniform noise; the other kinds
    have its standard deviation), in edge lengths."""
    noise_kinds: tuple[NoiseKind, ...] = NOISE_KINDS
    """Noise models each draw's noise is drawn from, one per draw at random."""
    views: int = 6
    resolution: int = 256
    vertices_per_draw: int = 40_000
    """Seen vertices of each draw kept for training (at random; large meshes would dominate)."""
    steps: int = 4000
    minutes: float = 5.0
    batch: int = 4096
    lr: float = 1e-3


@dataclass(frozen=True)
class GainExample:
    """One noisy draw of a mesh as one method's update sees it."""

    name: str
    features: NDArray[np.float32]
    """(V, F) `gain_features` of the seen vertices kept."""
    target: NDArray[np.float32]
    """(V,) the move along the normal that puts each vertex on the truth, in edge lengths."""


@dataclass(frozen=True)
class GainDraw:
    """A draw with everything each method's update needs, for training and validation."""

    name: str
    truth: TriangleMesh
    base: TriangleMesh
    """The pre-smoothed mesh the update moves."""
    edge_m: float
    """Mean edge length of the noisy mesh."""
    steps: dict[str, ViewSteps]
    """Method -> its view steps (the whole correction, gain 1)."""
    update: UpdateConfig
    """The update's `UpdateConfig` for the networks."""


def gain_draw(name: str, unit: TriangleMesh, config: GainTrainConfig,
              weights: dict[str, bytes] | None, rng: np.random.Generator) -> GainDraw:
    """A noisy draw of the unit-extent mesh, enhanced by every method of `config`."""
    truth, noisy = noisy_draw(unit, config.edge_fraction, config.noise_to_edge, rng,
                              config.noise_kinds)
    enhance = EnhanceConfig(views=config.views, resolution=config.resolution, weights=weights)
    inputs = update_inputs(noisy, enhance, resolve_device(enhance.device).type)
    steps = {}
    for method in config.methods:
        enhanced = enhance_renders(inputs.base_renders, inputs.renders,
                                   replace(enhance, method=method))
        steps[method] = view_steps(inputs.base, inputs.base_renders, enhanced, inputs.update)
    return GainDraw(name, truth, inputs.base, mean_edge_length_m(noisy), steps, inputs.update)


def gain_examples(
    meshes: Sequence[tuple[str, TriangleMesh]],
    config: GainTrainConfig,
    weights: dict[str, bytes] | None,
    rng: np.random.Generator,
    progress: Callable[[float], None] | None = None,
) -> dict[str, list[GainExample]]:
    """Per method, `draws_per_mesh` examples of each mesh (the same vertices for every method);
    procedural shapes only `with_procedural`."""
    if not config.with_procedural:
        meshes = [(name, mesh) for name, mesh in meshes if not name.startswith(PROCEDURAL)]
    out: dict[str, list[GainExample]] = {m: [] for m in config.methods}
    total, done = len(meshes) * config.draws_per_mesh, 0
    for name, mesh in meshes:
        unit = unit_extent(mesh, name)
        for _ in range(config.draws_per_mesh):
            draw = gain_draw(name, unit, config, weights, rng)
            target = -signed_c2m(draw.base.vertices_m, draw.truth) / draw.edge_m
            keep = np.flatnonzero(next(iter(draw.steps.values())).seen)
            if len(keep) > config.vertices_per_draw:
                keep = rng.choice(keep, config.vertices_per_draw, replace=False)
            for method, steps in draw.steps.items():
                features = gain_features(steps, draw.edge_m)[keep]
                out[method].append(GainExample(name, features, target[keep].astype(np.float32)))
            done += 1
            if progress is not None:
                progress(done / total)
    return out


def gain_loss(gain: torch.Tensor, features: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared distance to the truth, along the normal, of vertices moved by their gain
    times their mean view step."""
    return ((target - gain * features[:, MEAN_STEP]) ** 2).mean()


def train_gain(
    examples: Sequence[GainExample],
    config: GainTrainConfig,
    seed: int,
    progress: Callable[[float, str], None] | None = None,
) -> tuple[VertexGainNet, dict]:
    """The trained gain network, and {steps, train_seconds, final_loss}."""
    torch.manual_seed(seed)
    features = torch.from_numpy(np.concatenate([e.features for e in examples]))
    target = torch.from_numpy(np.concatenate([e.target for e in examples]))
    model = VertexGainNet(config.model)
    model.set_normalisation(features)

    def batch_loss(i: torch.Tensor) -> torch.Tensor:
        return gain_loss(model(features[i]), features[i], target[i])

    log = fit_rows(model, len(features), batch_loss, config.steps, config.minutes, config.batch,
                   config.lr, seed, progress, "gain")
    return model, log


def validate_gain(
    models: dict[str, VertexGainNet],
    meshes: Sequence[tuple[str, TriangleMesh]],
    config: GainTrainConfig,
    weights: dict[str, bytes] | None,
    rng: np.random.Generator,
) -> dict[str, dict[str, float]]:
    """Per held-out mesh (one draw each), RMS distance to the truth in permille of the extent
    of: the pre-smoothed mesh, and each method's update with `FIXED_GAIN` and with its
    learned gains (no light remesh)."""
    fixed = FIXED_GAIN
    out = {}
    for name, mesh in meshes:
        draw = gain_draw(name, unit_extent(mesh, name), config, weights, rng)

        def rms(v: NDArray[np.float64], truth: TriangleMesh = draw.truth) -> float:
            return float(np.sqrt(np.mean(signed_c2m(v, truth) ** 2)) * 1e3)

        figures = {"presmoothed": rms(draw.base.vertices_m)}
        for method, model in models.items():
            steps = draw.steps[method]
            gain = vertex_gains(model, gain_features(steps, draw.edge_m))
            for label, g in ((f"{method}_fixed_gain", np.full(len(gain), fixed)),
                             (f"{method}_learned_gain", gain)):
                moved, _ = apply_view_steps(draw.base, steps, draw.update, g)
                figures[label] = rms(moved.vertices_m)
        out[name] = figures
    return out
