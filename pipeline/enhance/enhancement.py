"""`enhance_mesh`: render views, enhance them with the chosen method, move the vertices."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.config import EnhanceConfig, validate_config
from pipeline.enhance.networks import (
    NETWORK_METHODS,
    EnhanceNetworks,
    load_networks,
    selector_for,
)
from pipeline.enhance.noise_level import noise_to_edge_ratio
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
from pipeline.geometry.order import reordered, restored, spatial_order
from pipeline.reconstruct.remesh.isotropic import RemeshConfig, kernel_piece_count, remesh
from pipeline.reconstruct.remesh.kernel import KernelChild, kernel_children
from pipeline.reconstruct.remesh.speculative import (
    CheckedFaces,
    RemeshAhead,
    carried_with_angles,
    checked_faces,
    finish_remesh_ahead,
    start_remesh_ahead,
)

STAGE_PROGRESS = {"render": 0.03, "presmooth": 0.33, "network": 0.5, "update": 0.54,
                  "remesh": 1.0}
"""Share of a network method's work done after each stage (the bunny on 2 CPU cores): what
`enhance_mesh` reports to its `progress` callback as each stage ends."""
CHECKED_STAGE_PROGRESS = {"render": 0.02, "presmooth": 0.17, "check": 0.65, "network": 0.74,
                          "update": 0.76, "remesh": 1.0}
"""`STAGE_PROGRESS` with the self-check (`EnhanceConfig.self_check`), which took 0.9 of the
rest's time on the bunny (2 cores). Where the check keeps the classical result, "remesh"
follows "check"."""


def enhance_mesh(
    mesh: TriangleMesh,
    config: EnhanceConfig,
    progress: Callable[[float], None] | None = None,
    networks: EnhanceNetworks | None = None,
    on_check: Callable[[SelfCheck], None] | None = None,
) -> TriangleMesh:
    """The mesh with vertices moved; the view-based methods end with a light remesh
    (``remesh_iterations``), the smoothers keep the connectivity. The networks return a mesh
    less noisy than ``min_noise_ratio`` as it came (`skips_enhancement`), and with
    ``self_check`` the classical result where they lose on a simulated copy (`self_check.py`;
    `on_check` is told the figures).

    `networks`: the networks `config` runs, loaded beforehand (`networks.load_networks`) and
    kept between meshes; None: loaded here, each as its stage begins (with ``self_check``,
    once for both uses)."""
    from pipeline.enhance.inference import selector_presmoothed
    from pipeline.geometry import smoothing as baselines

    validate_config(config)
    if mesh.vertex_count == 0 or mesh.face_count == 0:
        raise ValueError("mesh: has no vertices or no faces")
    non_finite = int(np.count_nonzero(~np.isfinite(mesh.vertices_m).all(axis=1)))
    if non_finite:
        raise ValueError(f"mesh: {non_finite} vertices have a coordinate that is not finite")
    if networks is not None and not networks.fits(config):
        raise ValueError("networks: loaded for another method, device or weights than "
                         "the config's")
    if config.method == "taubin":
        return baselines.taubin_smooth(mesh, config.iterations)
    if config.method == "laplacian":
        return baselines.laplacian_smooth(mesh, config.iterations)
    if config.method == "twicing":
        return baselines.twicing_smooth(mesh, config.iterations)
    if config.method == "adaptive":
        return baselines.adaptive_twicing(mesh, baselines.AdaptiveTwicingConfig())
    if config.method == "bilateral":
        return baselines.bilateral_denoise(mesh, config.iterations)
    from pipeline.enhance.device import resolve_device

    device = resolve_device(config.device).type
    if config.method == "selector":
        # In the canonical order, as the view methods run, so that the result does not
        # depend on how the input lists its vertices and faces.
        order = spatial_order(mesh)
        selector = selector_for(config, networks)
        return restored(selector_presmoothed(reordered(mesh, order), selector,
                                             config.bounded_noise, device), order)

    shares = CHECKED_STAGE_PROGRESS if self_checks(config) else STAGE_PROGRESS

    def done(stage: str) -> None:
        if progress is not None:
            progress(shares[stage])

    # The light remesh's kernel children start now: their interpreters start and import
    # while the stages before the remesh run.
    pieces = kernel_piece_count(mesh.face_count, None) if config.remesh_iterations > 0 else 0
    if self_checks(config) and networks is None:
        networks = load_networks(config)
    with kernel_children(pieces) as children:
        return _enhanced_by_views(mesh, config, device, done, children, networks,
                                  on_check or (lambda check: None))


def _enhanced_by_views(mesh: TriangleMesh, config: EnhanceConfig, device: str,
                       done: Callable[[str], None], children: Sequence[KernelChild],
                       networks: EnhanceNetworks | None,
                       on_check: Callable[[SelfCheck], None]) -> TriangleMesh:
    """`enhance_mesh` of the view-based methods, the light remesh's kernel in `children`,
    the `networks` given (None: loaded as their stages begin)."""
    from pipeline.enhance.device import accelerator

    # The stages gather neighbours all over the mesh; in a spatial order they hit the cache.
    # The order is canonical, so the result depends on the surface alone, not on how the
    # input lists its vertices and faces.
    order = spatial_order(mesh)
    ordered = reordered(mesh, order)
    # The noise gate (numpy) runs beside the render (open3d), both free of the GIL in their
    # loops. Loading the networks beside the pre-smoothing was slower on 2 cores: two
    # threads' torch ops each ask for every core (bunny 5.2-6.2 s against 4.9-5.1 s).
    ahead = config.remesh_iterations > 0 and remeshes_ahead(config)
    with ThreadPoolExecutor(max_workers=1) as pool:
        gate = pool.submit(skips_enhancement, ordered, config, device)
        # The update keeps the faces: the remesh ahead reads what they need beside the render
        # and the pre-smoothing (waited for at the render's end, they took the device host's
        # render from 0.05 to 0.21-0.23 s).
        checked = pool.submit(checked_faces, ordered) if ahead else None
        renders = render_depth(ordered, views_for(ordered, config), with_color=True,
                               device=accelerator(device))
        if gate.result():
            done("remesh")
            return mesh
        inputs = update_inputs(ordered, config, device, done, renders, networks)
    done("presmooth")
    if self_checks(config):
        classical = normal_filter(inputs.base, config.normal_filter, device)
        check = _self_checked(ordered, inputs, classical, config, device, networks)
        on_check(check)
        done("check")
        if not check.networks_help:
            kept = (restored(classical, order) if config.remesh_iterations == 0 else
                    light_remesh(classical, config.remesh_iterations, children))
            done("remesh")
            return kept
    if config.remesh_iterations == 0:  # the output keeps the input's order
        kept = restored(_updated(ordered, inputs, config, device, done, networks), order)
        done("remesh")
        return kept
    result = (_updated_remeshed_ahead(ordered, inputs, config, device, done, children,
                                      checked.result() if checked is not None else None,
                                      networks)
              if ahead else
              light_remesh(_updated(ordered, inputs, config, device, done, networks),
                           config.remesh_iterations, children))
    done("remesh")
    return result


def self_checks(config: EnhanceConfig) -> bool:
    """Whether `enhance_mesh` runs the self-check: ``self_check`` on a network method."""
    return config.self_check and config.method in NETWORK_METHODS


def _self_checked(ordered: TriangleMesh, inputs: UpdateInputs, classical: TriangleMesh,
                  config: EnhanceConfig, device: str, networks: EnhanceNetworks | None
                  ) -> SelfCheck:
    """The networks' update and the `classical` ending (the base, then the normal filter)
    compared on a copy of `classical` as noisy as the mesh (`self_check.simulated_copy`),
    pre-smoothed and enhanced as the mesh is."""
    copy = simulated_copy(ordered, inputs.base, classical, config.seed)
    copy_inputs = update_inputs(copy, config, device, networks=networks)
    without_networks = normal_filter(copy_inputs.base, config.normal_filter, device)
    with_networks = _updated(copy, copy_inputs, config, device, lambda stage: None, networks)
    return scored(without_networks, with_networks, classical)


def remeshes_ahead(config: EnhanceConfig) -> bool:
    """Whether the light remesh starts ahead of the update (`EnhanceConfig.remesh_ahead`; by
    default where the device is an accelerator)."""
    from pipeline.enhance.device import accelerator, resolve_device

    if config.remesh_ahead is not None:
        return config.remesh_ahead
    return accelerator(resolve_device(config.device).type) is not None


def _updated_remeshed_ahead(ordered: TriangleMesh, inputs: UpdateInputs, config: EnhanceConfig,
                            device: str, done: Callable[[str], None],
                            children: Sequence[KernelChild], checked: CheckedFaces | None,
                            networks: EnhanceNetworks | None) -> TriangleMesh:
    """`_updated`, its light remesh started on the base beside the networks and the update,
    in `children`, and carried onto the moved base (`remesh_ahead`; `checked`: the base's
    faces, checked beforehand). What starts it (repair, split, order, pieces) runs in a
    thread: on a GPU the host has little else to do. There the result is carried onto the
    moved base on the device (`carry_torch`)."""
    from pipeline.enhance.clean.transfer_torch import carried_on
    from pipeline.enhance.device import accelerator

    def start() -> RemeshAhead | None:
        remesh_config = light_remesh_config(inputs.base, config.remesh_iterations)
        return start_remesh_ahead(inputs.base, remesh_config, children, checked)

    with ThreadPoolExecutor(max_workers=1) as pool:
        starting = pool.submit(start)
        result = _updated(ordered, inputs, config, device, done, networks)
        ahead = starting.result()
    if ahead is None:  # the repair dropped vertices: remesh the moved mesh
        return light_remesh(result, config.remesh_iterations, children)
    there = accelerator(device)
    return finish_remesh_ahead(ahead, result,
                               carried_with_angles if there is None else carried_on(there))[0]


def _updated(ordered: TriangleMesh, inputs: UpdateInputs, config: EnhanceConfig, device: str,
             done: Callable[[str], None], networks: EnhanceNetworks | None) -> TriangleMesh:
    """The networks' correction of the renders of `inputs`, the view update that follows it
    and the normal filter: the base moved."""
    from pipeline.enhance.device import accelerator

    learned = config.learned_gain and config.method != "views"
    enhanced = enhance_renders(inputs.base_renders, inputs.renders,
                               replace(config, correction_gain=1.0) if learned else config,
                               None if networks is None else networks.enhancer)
    done("network")
    steps = view_steps(inputs.base, inputs.base_renders, enhanced, inputs.update,
                       accelerator(device))
    gain = (learned_vertex_gain(ordered, steps, config, device,
                                None if networks is None else networks.gain)
            if learned else None)
    result, _ = apply_view_steps(inputs.base, steps, inputs.update, gain, accelerator(device))
    result = normal_filter(result, config.normal_filter, device)
    done("update")
    return result


@dataclass(frozen=True)
class UpdateInputs:
    """What the view-based methods enhance and move."""

    renders: DepthRenders
    """The mesh's own renders, with colour (the networks' side input)."""
    base: TriangleMesh
    """The mesh the update moves: the pre-smoothed mesh (the networks), or the mesh (views)."""
    base_renders: DepthRenders
    """The base's renders, which the networks correct."""
    update: UpdateConfig
    """The update's settings for this method."""


def views_for(mesh: TriangleMesh, config: EnhanceConfig) -> ViewSet:
    """The views `config` renders `mesh` from."""
    return make_views(mesh.vertices_m, view_directions(config.views), config.resolution)


def update_inputs(
    mesh: TriangleMesh, config: EnhanceConfig, device: str,
    done: Callable[[str], None] = lambda stage: None, renders: DepthRenders | None = None,
    networks: EnhanceNetworks | None = None,
) -> UpdateInputs:
    """Renders the mesh from `views_for` (unless its `renders`, with colour, are given),
    calls `done("render")`, and pre-smooths it (smoothing steps on `device`) as
    `config.method` wants, with the selector of `networks` (None: loaded here)."""
    from pipeline.enhance.device import accelerator
    from pipeline.enhance.inference import presmoothed

    if renders is None:
        renders = render_depth(mesh, views_for(mesh, config), with_color=True,
                               device=accelerator(device))
    views = renders.views
    done("render")
    base, base_renders, update = mesh, renders, config.update
    if config.method != "views" and config.presmooth_iterations > 0:
        selector = selector_for(config, networks) if config.presmooth_learned else None
        base = presmoothed(mesh, config.presmooth_iterations, config.presmooth_passes,
                           config.presmooth_adaptive, selector, device, config.bounded_noise)
        base_renders = render_depth(base, views, with_color=False, device=accelerator(device))
        update = replace(update, unseen_follow_moves=True)
    if config.method != "views":
        update = replace(update, follow_change=True)
    return UpdateInputs(renders, base, base_renders, update)


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


def skips_enhancement(mesh: TriangleMesh, config: EnhanceConfig, device: str | None = None
                      ) -> bool:
    """Whether `enhance_mesh` leaves `mesh` as it is: a network method on a mesh whose
    estimated noise is below `config.min_noise_ratio` (estimated on `device` where it is an
    accelerator)."""
    if not gated(config):
        return False
    from pipeline.enhance.device import accelerator

    return skipped_at(noise_to_edge_ratio(mesh, accelerator(device)), config)


def gated(config: EnhanceConfig) -> bool:
    """Whether `config`'s method leaves a mesh less noisy than `min_noise_ratio` as it is."""
    return config.method in NETWORK_METHODS and config.min_noise_ratio > 0


def skipped_at(noise_ratio: float, config: EnhanceConfig) -> bool:
    """Whether `enhance_mesh` leaves a mesh of this `noise_to_edge_ratio` as it is."""
    return gated(config) and noise_ratio < config.min_noise_ratio


def past_the_gate(config: EnhanceConfig) -> EnhanceConfig:
    """`config` for a mesh its caller has already measured past the noise gate
    (`skipped_at`): `enhance_mesh` then neither measures the noise again nor decides
    otherwise, on a GPU in torch, near the line."""
    return replace(config, min_noise_ratio=0.0)


LIGHT_REMESH_MAX_ADDED_OUTSIDE = 2e-4
"""The light remesh's kernel is dropped where it adds more than this share of faces outside
the angle criteria. Under the benchmark's protocol as it was before long boundary edges were
split it added 0.14 % (suzanne) and 0.16 % (beetle), where it did harm; 0.002 % (cheburashka,
a few faces) or none, where it helped. Under the protocol now it keeps the kernel on suzanne,
where it does harm (1.0123 -> 1.0265 mm); not re-tuned on the benchmark's meshes:
`LIGHT_REMESH_MAX_LOST_EDGES` drops it there."""

LIGHT_REMESH_GRID_M = 2.0**-32
"""The grid `light_remesh` snaps vertices to, metres (0.23 nm): far below any mesh's detail,
far above float64's rounding of coordinates of a few metres (4e-16 m at 1 m), and exact
(a power of two) for coordinates below 2^21 m."""

LIGHT_REMESH_MAX_LOST_EDGES = 2.0
"""The light remesh's kernel is dropped where an input vertex ends up further than this many
edge lengths from every vertex of its result (`remesh.surface_lost_edges`). On the LDM's updates
of the benchmark's ten meshes (fourteenth session) it was 0.6-1.0 where the kernel helped, and
6.2 on suzanne, whose update keeps faces tens of edges long that one round of the kernel cuts
across, where it did harm (0.9837 mm without the light remesh, 0.9986 with it, 0.9806 with the
clean-up alone)."""


def light_remesh(mesh: TriangleMesh, iterations: int, children: Sequence[KernelChild] = ()
                 ) -> TriangleMesh:
    """The mesh remeshed at its own mean edge length (vertices projected back onto it), unless
    that adds faces outside the angle criteria (`LIGHT_REMESH_MAX_ADDED_OUTSIDE`) or cuts part
    of the surface away (`LIGHT_REMESH_MAX_LOST_EDGES`), then its angles cleaned up. Under the
    benchmark's earlier protocol the isotropic kernel added such faces to beetle's and
    suzanne's updates and left them further from the truth both ways (C2M RMS 0.985 / 1.062
    mm, against 0.950 / 1.021 with the clean-up alone), while it took 0.25-1.9 % off the C2M
    RMS of the other eight meshes (`benchmarks/enhance_remesh.py`). The kernel runs in
    spatial pieces side by side, one per core (`remesh_pieces`): at the mesh's own edge
    length the held cuts cost nothing measurable (the bunny's LDM update 0.66126 against
    0.66128 mm), and on 2 cores two pieces take 10-15 % off the light remesh
    (`benchmarks/remesh_speed.py`).

    The mesh is first snapped to a grid of `LIGHT_REMESH_GRID_M`: the kernel compares edge
    lengths with each other and with the target, and where a mesh has edges of equal length
    (a symmetric one) a difference of rounding alone, such as a GPU's float64 sums against
    the host's (1e-15 m on the tests' sphere), chose other flips and gave another mesh."""
    mesh = on_light_remesh_grid(mesh)
    return remesh(mesh, light_remesh_config(mesh, iterations), children)[0]


def on_light_remesh_grid(mesh: TriangleMesh) -> TriangleMesh:
    """`mesh` with its vertices snapped to `LIGHT_REMESH_GRID_M`."""
    return replace(mesh, vertices_m=np.round(mesh.vertices_m / LIGHT_REMESH_GRID_M)
                   * LIGHT_REMESH_GRID_M)


def light_remesh_config(mesh: TriangleMesh, iterations: int) -> RemeshConfig:
    """`light_remesh`'s settings for `mesh`: its own mean edge length, `iterations` rounds,
    the kernel judged and in pieces, one per core."""
    return RemeshConfig(target_edge_length_m=mean_edge_length_m(mesh), iterations=iterations,
                        max_kernel_added_outside=LIGHT_REMESH_MAX_ADDED_OUTSIDE,
                        max_kernel_lost_edges=LIGHT_REMESH_MAX_LOST_EDGES,
                        min_component_share=0.0, kernel_processes=None)


def enhance_renders(
    base: DepthRenders, noisy: DepthRenders, config: EnhanceConfig, enhancer=None
) -> NDArray[np.float32]:
    """(N, H, W) enhanced normalised depth of all views, in one batch: `base` (the
    pre-smoothed mesh's renders) moved by `config.correction_gain` of the network's correction,
    `noisy` (the mesh's own renders) read beside it; `enhancer`: the network loaded beforehand
    (`loading.load_enhancer`; None: loaded here)."""
    if config.method == "views":
        return base.depth_n
    from pipeline.enhance.inference import run_network

    predicted = run_network(base, noisy, config, enhancer)
    return base.depth_n + config.correction_gain * (predicted - base.depth_n)
