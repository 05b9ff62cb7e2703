"""`enhance_mesh`: one forward, in stages, for every method.

render -> pre-smooth -> correct -> update -> clean. The mesh's depth views are rendered
(`render/`); the mesh is pre-smoothed by the selector's blend of twicings and the midrange
estimator (`presmooth/`) and rendered again; the depth network corrects those renders; the
vertices follow the correction, each by the share its vertex gain network gives, and the
bilateral normal filter ends the update (`update/`); the light remesh cleans up (`clean/`).
The classical method runs the same forward without render and correct.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.clean.light_remesh import light_remesh, light_remesh_config
from pipeline.enhance.config import NETWORK_METHODS, EnhanceConfig, validate_config
from pipeline.enhance.inference import selector_presmoothed
from pipeline.enhance.networks import EnhanceNetworks, load_networks, selector_for
from pipeline.enhance.noise_level import gated, past_the_gate, skipped_at, skips_enhancement
from pipeline.enhance.render.views import (
    DepthRenders,
    ViewSet,
    make_views,
    render_depth,
    view_directions,
)
from pipeline.enhance.self_check import SelfCheck, scored, simulated_copy
from pipeline.enhance.update.normal_filter import normal_filter
from pipeline.enhance.update.steps import UpdateConfig, ViewSteps, apply_view_steps, view_steps
from pipeline.geometry.mesh import TriangleMesh, mean_edge_length_m
from pipeline.geometry.order import MeshOrder, reordered, restored, spatial_order
from pipeline.reconstruct.remesh.isotropic import kernel_piece_count
from pipeline.reconstruct.remesh.kernel import KernelChild, kernel_children
from pipeline.reconstruct.remesh.speculative import (
    CheckedFaces,
    RemeshAhead,
    carried_with_angles,
    checked_faces,
    finish_remesh_ahead,
    start_remesh_ahead,
)

__all__ = ["CHECKED_STAGE_PROGRESS", "CLASSICAL_STAGE_PROGRESS", "STAGE_PROGRESS",
           "UpdateInputs", "enhance_mesh", "enhance_renders", "gated", "learned_vertex_gain",
           "past_the_gate", "remeshes_ahead", "self_checks", "skipped_at", "skips_enhancement",
           "update_inputs", "views_for"]

STAGE_PROGRESS = {"render": 0.03, "presmooth": 0.33, "network": 0.5, "update": 0.54,
                  "remesh": 1.0}
"""Share of a network method's work done after each stage (the bunny on 2 CPU cores): what
`enhance_mesh` reports to its `progress` callback as each stage ends."""
CHECKED_STAGE_PROGRESS = {"render": 0.02, "presmooth": 0.17, "check": 0.65, "network": 0.74,
                          "update": 0.76, "remesh": 1.0}
"""`STAGE_PROGRESS` with the self-check (`EnhanceConfig.self_check`). Where the check keeps
the classical result, "remesh" follows "check"."""
CLASSICAL_STAGE_PROGRESS = {"presmooth": 0.5, "update": 0.7, "remesh": 1.0}
"""`STAGE_PROGRESS` of the classical method, which neither renders nor runs a depth network."""


@dataclass(frozen=True)
class _Run:
    """What the stages of one `enhance_mesh` call share."""

    config: EnhanceConfig
    device: str
    """The resolved torch device type."""
    networks: EnhanceNetworks | None
    """The networks loaded beforehand; None: each stage loads its own."""
    children: Sequence[KernelChild]
    """The light remesh's kernel children, started as the call began."""
    done: Callable[[str], None]
    """Told each stage's name as it ends."""


def enhance_mesh(
    mesh: TriangleMesh,
    config: EnhanceConfig,
    progress: Callable[[float], None] | None = None,
    networks: EnhanceNetworks | None = None,
    on_check: Callable[[SelfCheck], None] | None = None,
) -> TriangleMesh:
    """The mesh enhanced by `config.method`, light-remeshed (``remesh_iterations``); a mesh
    less noisy than ``min_noise_ratio`` as it came, and with ``self_check`` the classical
    result where the networks lose on a simulated copy (`self_check.py`; `on_check` is told
    the figures). The result depends on the surface alone, not on how the input lists its
    vertices and faces.

    `networks`: the networks `config` runs, loaded beforehand (`networks.load_networks`) and
    kept between meshes; None: loaded here, each as its stage begins (with ``self_check``,
    once for both uses)."""
    from pipeline.enhance.device import resolve_device

    _check_inputs(mesh, config, networks)
    shares = stage_progress(config)

    def done(stage: str) -> None:
        if progress is not None:
            progress(shares[stage])

    # The kernel children start first: their interpreters start and import while the stages
    # before the light remesh run.
    pieces = kernel_piece_count(mesh.face_count, None) if config.remesh_iterations > 0 else 0
    if self_checks(config) and networks is None:
        networks = load_networks(config)
    with kernel_children(pieces) as children:
        run = _Run(config, resolve_device(config.device).type, networks, children, done)
        # The stages gather neighbours all over the mesh; in a spatial order they hit the
        # cache. The order is canonical, so the result does not depend on the input's.
        order = spatial_order(mesh)
        forward = _classical if config.method == "classical" else _by_networks
        return forward(mesh, order, run, on_check or (lambda check: None))


def _check_inputs(mesh: TriangleMesh, config: EnhanceConfig,
                  networks: EnhanceNetworks | None) -> None:
    """Raises ValueError naming what `enhance_mesh` cannot run on."""
    validate_config(config)
    if mesh.vertex_count == 0 or mesh.face_count == 0:
        raise ValueError("mesh: has no vertices or no faces")
    non_finite = int(np.count_nonzero(~np.isfinite(mesh.vertices_m).all(axis=1)))
    if non_finite:
        raise ValueError(f"mesh: {non_finite} vertices have a coordinate that is not finite")
    if networks is not None and not networks.fits(config):
        raise ValueError("networks: loaded for another method, device or weights than "
                         "the config's")


def stage_progress(config: EnhanceConfig) -> dict[str, float]:
    """The shares `enhance_mesh` reports for `config`, by stage."""
    if config.method == "classical":
        return CLASSICAL_STAGE_PROGRESS
    return CHECKED_STAGE_PROGRESS if self_checks(config) else STAGE_PROGRESS


def _classical(mesh: TriangleMesh, order: MeshOrder, run: _Run,
               on_check: Callable[[SelfCheck], None]) -> TriangleMesh:
    """pre-smooth -> update (the normal filter alone) -> clean: no render, no network."""
    ordered = reordered(mesh, order)
    if skips_enhancement(ordered, run.config, run.device):
        run.done("remesh")
        return mesh
    base = selector_presmoothed(ordered, selector_for(run.config, run.networks),
                                run.config.bounded_noise, run.device)
    run.done("presmooth")
    result = normal_filter(base, run.config.normal_filter, run.device)
    run.done("update")
    return _cleaned(result, order, run)


def _by_networks(mesh: TriangleMesh, order: MeshOrder, run: _Run,
                 on_check: Callable[[SelfCheck], None]) -> TriangleMesh:
    """render -> pre-smooth -> [self-check] -> correct -> update -> clean."""
    from pipeline.enhance.device import accelerator

    ordered = reordered(mesh, order)
    ahead = run.config.remesh_iterations > 0 and remeshes_ahead(run.config)
    # The noise gate (numpy) runs beside the render (open3d), both free of the GIL in their
    # loops; the speculative remesh reads the faces it needs there too.
    with ThreadPoolExecutor(max_workers=1) as pool:
        gate = pool.submit(skips_enhancement, ordered, run.config, run.device)
        checked = pool.submit(checked_faces, ordered) if ahead else None
        renders = render_depth(ordered, views_for(ordered, run.config), with_color=True,
                               device=accelerator(run.device))
        if gate.result():
            run.done("remesh")
            return mesh
        inputs = update_inputs(ordered, run.config, run.device, run.done, renders,
                               run.networks)
    run.done("presmooth")
    if self_checks(run.config):
        classical = normal_filter(inputs.base, run.config.normal_filter, run.device)
        check = _self_checked(ordered, inputs, classical, run)
        on_check(check)
        run.done("check")
        if not check.networks_help:
            return _cleaned(classical, order, run)
    if checked is not None:
        result = _updated_remeshed_ahead(ordered, inputs, run, checked.result())
        run.done("remesh")
        return result
    return _cleaned(_updated(ordered, inputs, run), order, run)


def _cleaned(result: TriangleMesh, order: MeshOrder, run: _Run) -> TriangleMesh:
    """clean: the light remesh of `result` (in the spatial order), or with no rounds `result`
    in the input's order."""
    kept = (restored(result, order) if run.config.remesh_iterations == 0 else
            light_remesh(result, run.config.remesh_iterations, run.children))
    run.done("remesh")
    return kept


def self_checks(config: EnhanceConfig) -> bool:
    """Whether `enhance_mesh` runs the self-check: ``self_check`` on a network method."""
    return config.self_check and config.method in NETWORK_METHODS


def _self_checked(ordered: TriangleMesh, inputs: UpdateInputs, classical: TriangleMesh,
                  run: _Run) -> SelfCheck:
    """The networks' update and the `classical` ending (the base, then the normal filter)
    compared on a copy of `classical` as noisy as the mesh (`self_check.simulated_copy`),
    pre-smoothed and enhanced as the mesh is."""
    quiet = replace(run, done=lambda stage: None)
    copy = simulated_copy(ordered, inputs.base, classical, run.config.seed)
    copy_inputs = update_inputs(copy, run.config, run.device, networks=run.networks)
    without_networks = normal_filter(copy_inputs.base, run.config.normal_filter, run.device)
    with_networks = _updated(copy, copy_inputs, quiet)
    return scored(without_networks, with_networks, classical)


def remeshes_ahead(config: EnhanceConfig) -> bool:
    """Whether the light remesh starts ahead of the update (`EnhanceConfig.remesh_ahead`; by
    default where the device is an accelerator)."""
    from pipeline.enhance.device import accelerator, resolve_device

    if config.remesh_ahead is not None:
        return config.remesh_ahead
    return accelerator(resolve_device(config.device).type) is not None


def _updated_remeshed_ahead(ordered: TriangleMesh, inputs: UpdateInputs, run: _Run,
                            checked: CheckedFaces | None) -> TriangleMesh:
    """`_updated`, its light remesh started on the base beside the networks and the update
    and carried onto the moved base (speculative remesh; `checked`: the base's faces, checked
    beforehand). What starts it (repair, split, order, pieces) runs in a thread: on a GPU the
    host has little else to do. There the result is carried onto the moved base on the
    device (`carried_on`)."""
    from pipeline.enhance.clean.transfer_torch import carried_on
    from pipeline.enhance.device import accelerator

    def start() -> RemeshAhead | None:
        remesh_config = light_remesh_config(inputs.base, run.config.remesh_iterations)
        return start_remesh_ahead(inputs.base, remesh_config, run.children, checked)

    with ThreadPoolExecutor(max_workers=1) as pool:
        starting = pool.submit(start)
        result = _updated(ordered, inputs, run)
        ahead = starting.result()
    if ahead is None:  # the repair dropped vertices: remesh the moved mesh
        return light_remesh(result, run.config.remesh_iterations, run.children)
    there = accelerator(run.device)
    return finish_remesh_ahead(ahead, result,
                               carried_with_angles if there is None else carried_on(there))[0]


def _updated(ordered: TriangleMesh, inputs: UpdateInputs, run: _Run) -> TriangleMesh:
    """correct -> update: the network's correction of the base's renders, each vertex
    following its own share of it, then the normal filter: the base moved."""
    from pipeline.enhance.device import accelerator

    networks = run.networks
    enhanced = enhance_renders(inputs.base_renders, inputs.renders, run.config,
                               None if networks is None else networks.enhancer)
    run.done("network")
    steps = view_steps(inputs.base, inputs.base_renders, enhanced, inputs.update,
                       accelerator(run.device))
    gain = learned_vertex_gain(ordered, steps, run.config, run.device,
                               None if networks is None else networks.gain)
    result, _ = apply_view_steps(inputs.base, steps, inputs.update, gain,
                                 accelerator(run.device))
    result = normal_filter(result, run.config.normal_filter, run.device)
    run.done("update")
    return result


@dataclass(frozen=True)
class UpdateInputs:
    """What the networks correct and the update moves."""

    renders: DepthRenders
    """The mesh's own renders, with colour (the networks' side input)."""
    base: TriangleMesh
    """The mesh the update moves: the pre-smoothed mesh."""
    base_renders: DepthRenders
    """The base's renders, which the networks correct."""
    update: UpdateConfig
    """The update's settings."""


def views_for(mesh: TriangleMesh, config: EnhanceConfig) -> ViewSet:
    """The views `config` renders `mesh` from."""
    return make_views(mesh.vertices_m, view_directions(config.views), config.resolution)


def update_inputs(
    mesh: TriangleMesh, config: EnhanceConfig, device: str,
    done: Callable[[str], None] = lambda stage: None, renders: DepthRenders | None = None,
    networks: EnhanceNetworks | None = None,
) -> UpdateInputs:
    """render -> pre-smooth: the mesh's renders from `views_for` (unless given, with colour),
    `done("render")`, then the mesh pre-smoothed (smoothing steps on `device`, the selector
    of `networks`, None: loaded here) and rendered from the same views."""
    from pipeline.enhance.device import accelerator

    if renders is None:
        renders = render_depth(mesh, views_for(mesh, config), with_color=True,
                               device=accelerator(device))
    done("render")
    base = selector_presmoothed(mesh, selector_for(config, networks), config.bounded_noise,
                                device)
    base_renders = render_depth(base, renders.views, with_color=False,
                                device=accelerator(device))
    return UpdateInputs(renders, base, base_renders, config.update)


def learned_vertex_gain(
    mesh: TriangleMesh, steps: ViewSteps, config: EnhanceConfig, device: str = "cpu",
    model=None,
) -> NDArray[np.float64]:
    """(V,) each vertex's share of the correction, from the method's gain network on
    `device`: `model`, loaded beforehand (`loading.load_vertex_gain`), else loaded here."""
    from pipeline.enhance.inference import vertex_gains
    from pipeline.enhance.update.vertex_gain import gain_features
    from pipeline.enhance.weights.loading import load_vertex_gain, model_bytes

    if model is None:
        model = load_vertex_gain(model_bytes(config, f"{config.method}_gain"))
    return vertex_gains(model, gain_features(steps, mean_edge_length_m(mesh)), device)


def enhance_renders(
    base: DepthRenders, noisy: DepthRenders, config: EnhanceConfig, enhancer=None
) -> NDArray[np.float32]:
    """(N, H, W) enhanced normalised depth of all views, in one batch: `base` (the
    pre-smoothed mesh's renders) moved by the network's whole correction, `noisy` (the mesh's
    own renders) read beside it; `enhancer`: the network loaded beforehand
    (`loading.load_enhancer`; None: loaded here)."""
    from pipeline.enhance.inference import run_network

    predicted = run_network(base, noisy, config, enhancer)
    # Base plus correction, not the prediction itself: the values the vertex gains were
    # trained on, to the last bit.
    return base.depth_n + (predicted - base.depth_n)
