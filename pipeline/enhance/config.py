"""`enhance_mesh`: render views, enhance them with the chosen method, move the vertices."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.bounded_noise import BoundedNoiseConfig
from pipeline.enhance.networks import EnhanceNetworks
from pipeline.enhance.noise_level import noise_to_edge_ratio
from pipeline.enhance.normal_filter import NormalFilterConfig, normal_filter
from pipeline.enhance.render import (
    DepthRenders,
    ViewSet,
    make_views,
    render_depth,
    view_directions,
)
from pipeline.enhance.update import UpdateConfig, ViewSteps, apply_view_steps, view_steps
from pipeline.mesh import TriangleMesh, mean_edge_length_m
from pipeline.mesh_order import reordered, restored, spatial_order
from pipeline.remesh import RemeshConfig, kernel_piece_count, remesh
from pipeline.remesh_ahead import (
    CheckedFaces,
    RemeshAhead,
    checked_faces,
    finish_remesh_ahead,
    start_remesh_ahead,
)
from pipeline.remesh_kernel import KernelChild, kernel_children

STAGE_PROGRESS = {"render": 0.03, "presmooth": 0.33, "network": 0.5, "update": 0.54,
                  "remesh": 1.0}
"""Share of a network method's work done after each stage (the bunny on 2 CPU cores): what
`enhance_mesh` reports to its `progress` callback as each stage ends."""

METHODS = (
    "ldm", "regressor", "views", "taubin", "laplacian", "twicing", "adaptive", "selector",
    "bilateral",
)


@dataclass(frozen=True)
class EnhanceConfig:
    """How to enhance a mesh."""

    method: str = "ldm"
    """ldm | regressor | views (raw renders into the update) | taubin | laplacian | twicing |
    adaptive (twicing, its count chosen per vertex) | selector (a learned per-vertex blend of
    twicings, `selector_presmoothed`) | bilateral."""
    views: int = 6
    """Number of depth views (the six axis views first)."""
    resolution: int = 256
    """Depth image side in pixels."""
    steps: int = 4
    """DDIM steps of the LDM (1 = one-step mode)."""
    strength: float = 0.5
    """How far into the noise schedule sampling starts from the degraded latent (0, 1]."""
    seed: int = 0
    """Seed of the LDM's start noise."""
    ensemble: int = 1
    """Geometric self-ensemble: the network runs on this many flips/transposes of each view
    (1, 2, 4 or 8) and the results, turned back, are averaged."""
    iterations: int = 8
    """Iterations of the classical smoothers."""
    presmooth_iterations: int = 30
    """Laplacian smoothing iterations before the networks (ldm, regressor), per pass (the
    pilot's count when adaptive): they correct the smoothed mesh's renders, reading the
    mesh's own as a side input, and the smoothed mesh's vertices move. Should match the
    weights' training (`DataConfig.presmooth_iterations`)."""
    presmooth_passes: int = 2
    """Passes of that smoothing (`twicing_smooth`; 1: plain Laplacian). Must match the
    weights' training (`DataConfig.presmooth_passes`)."""
    presmooth_adaptive: bool = True
    """Choose the pre-smoothing's count per vertex (`adaptive_twicing`, `presmooth_iterations`
    its pilot's count). The shipped weights were fine-tuned on fixed twicing at 30 and are fed
    this."""
    presmooth_learned: bool = True
    """The pre-smoothing is the selector's blend of twicings (`selector_presmoothed`, the
    `selector` weights; its candidates and pilot are fixed by those weights), in place of
    `presmooth_adaptive`'s choice; `presmooth_iterations` 0 still turns pre-smoothing off."""
    bounded_noise: BoundedNoiseConfig = field(default_factory=BoundedNoiseConfig)
    """The pre-smoothing (ldm, regressor, selector) ends by moving each vertex to the middle of
    its neighbourhood's residual range where the noise is bounded (`bounded_noise.py`; rings
    0: off)."""
    correction_gain: float = 0.7
    """Share of the networks' depth correction (enhanced minus base depth) the update
    follows, every vertex alike, when `learned_gain` is off. Chosen on the validation meshes
    (spot, fandisk; not the bunny) under the benchmark's protocol
    (`benchmarks/enhance_gain.py`), for the shipped LDM: C2M RMS at gains 0.1 / 0.2 / 0.35 /
    0.5 / 0.7 / 1.0 was 0.686 / 0.683 / 0.679 / 0.676 / 0.674 / 0.673 mm on spot and 0.723 /
    0.716 / 0.708 / 0.704 / 0.704 / 0.715 on fandisk; 0.7 gives the lowest mean. (0.35 was
    chosen while spot was read split along its texture seams, which the networks handled
    worse.)"""
    learned_gain: bool = True
    """Each vertex follows its own share of the networks' correction, given by the method's
    vertex gain network (`vertex_gain.py`; weights `ldm_gain`, `regressor_gain`) from how its
    views agree; False: every vertex follows `correction_gain`. On the validation meshes
    under the benchmark's protocol the LDM's mean C2M RMS went from 0.7427 mm (the best fixed
    gain) to 0.7314, the bunny's from 0.9190 to 0.9157."""
    min_noise_ratio: float = 0.05
    """The networks (ldm, regressor) leave a mesh unchanged whose estimated noise
    (`noise_to_edge_ratio`) is below this; 0 always enhances. Their pre-smoothing removes
    detail they cannot restore, so below some noise they do harm: on spot and fandisk under
    the benchmark's protocol with the noise amplitude swept (`benchmarks/enhance_gate.py`) the
    LDM's result matched the input's error at ratios 0.057 and 0.048 with the selector's
    pre-smoothing and the vertex gains (0.059 on spot read split along its texture seams;
    0.053 and 0.044 with one fixed gain, 0.072 and 0.064
    with adaptive twicing, 0.11 and 0.14 with ten Laplacian iterations). A reconstruction of
    the synthetic bunny capture measures 0.01 (enhanced without the gate: 0.70 -> 0.86 mm)."""
    update: UpdateConfig = field(default_factory=UpdateConfig)
    """How vertices follow the enhanced depth."""
    normal_filter: NormalFilterConfig = field(default_factory=NormalFilterConfig)
    """The bilateral normal filter that ends the view-based update (`normal_filter.py`;
    `normal_iterations` 0: off)."""
    remesh_iterations: int = 1
    """Rounds of a light isotropic remesh at the mesh's own mean edge length after the
    view-based update (the update itself already puts back moves that turn a face over),
    followed by the remesh stage's angle clean-up; the kernel's result is dropped where it
    adds faces outside the angle criteria (`light_remesh`); 0 keeps the connectivity. On
    the benchmark's bunny it takes the LDM from 0.9206 to 0.9172 mm C2M RMS (0.9192 to 0.9157
    under the protocol before long boundary edges were split, where it took the reverse RMS
    from 1.028 to 1.038 mm; `benchmarks/enhance_remesh.py`). It is 3.9 of the 7.0 s on 2 CPU
    cores and would be nearly all of the time on a GPU."""
    remesh_ahead: bool | None = None
    """Start the light remesh's kernel on the mesh the update moves, beside the networks, and
    carry its result onto the moved mesh (`pipeline.remesh_ahead`), rather than remesh the
    moved mesh after the update. None: where the device is an accelerator, whose host has
    cores to spare while the networks and the update run there; on 2 CPU cores the kernel
    only takes them from the networks (the bunny: no faster). The kernel's choices are then
    made on the surface before the update: 0.0-0.21 % more C2M RMS on the benchmark's ten
    meshes (the bunny's LDM 0.66126 -> 0.66218 mm)."""
    device: str = "auto"
    """Torch device for the networks: auto (CUDA when present), cpu or cuda."""
    weights: dict[str, bytes] | None = None
    """safetensors bytes per model ('regressor', 'vae', 'ldm', 'selector', 'ldm_gain',
    'regressor_gain'); None or a model left out: the shipped weights."""


def validate_config(config: EnhanceConfig) -> None:
    """Raises ValueError naming the first field of `config` that is out of range."""
    if config.method not in METHODS:
        raise ValueError(f"method: {config.method!r} is not one of {', '.join(METHODS)}")
    if config.views < 1:
        raise ValueError(f"views must be >= 1, got {config.views}")
    if config.resolution < 16:
        raise ValueError(f"resolution must be >= 16 pixels, got {config.resolution}")
    if config.steps < 1:
        raise ValueError(f"steps must be >= 1, got {config.steps}")
    if not 0.0 < config.strength <= 1.0:
        raise ValueError(f"strength must be in (0, 1], got {config.strength}")
    if config.ensemble not in (1, 2, 4, 8):
        raise ValueError(f"ensemble must be 1, 2, 4 or 8, got {config.ensemble}")
    if config.iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {config.iterations}")
    if not 0.0 < config.correction_gain <= 2.0:
        raise ValueError(f"correction_gain must be in (0, 2], got {config.correction_gain}")
    if config.min_noise_ratio < 0:
        raise ValueError(f"min_noise_ratio must be >= 0, got {config.min_noise_ratio}")
    if config.presmooth_iterations < 0:
        raise ValueError(
            f"presmooth_iterations must be >= 0, got {config.presmooth_iterations}"
        )
    if config.presmooth_passes < 1:
        raise ValueError(f"presmooth_passes must be >= 1, got {config.presmooth_passes}")
    if config.bounded_noise.rings < 0 or config.bounded_noise.smoothing < 0:
        raise ValueError(
            f"bounded_noise: rings and smoothing must be >= 0, got {config.bounded_noise.rings}"
            f" and {config.bounded_noise.smoothing}")
    if config.bounded_noise.weight_passes < 0:
        raise ValueError(
            f"bounded_noise: weight_passes must be >= 0, got {config.bounded_noise.weight_passes}")
    if config.remesh_iterations < 0:
        raise ValueError(f"remesh_iterations must be >= 0, got {config.remesh_iterations}")


def enhance_mesh(
    mesh: TriangleMesh,
    config: EnhanceConfig,
    progress: Callable[[float], None] | None = None,
    networks: EnhanceNetworks | None = None,
) -> TriangleMesh:
    """The mesh with vertices moved; the view-based methods end with a light remesh
    (``remesh_iterations``), the smoothers keep the connectivity. The networks return a mesh
    less noisy than ``min_noise_ratio`` as it came (`skips_enhancement`).

    `networks`: the networks `config` runs, loaded beforehand (`networks.load_networks`) and
    kept between meshes; None: loaded here, each as its stage begins."""
    from pipeline.enhance import baselines
    from pipeline.enhance.inference import load_selector, model_bytes, selector_presmoothed

    validate_config(config)
    if mesh.vertex_count == 0 or mesh.face_count == 0:
        raise ValueError("mesh: has no vertices or no faces")
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
        selector = (networks.selector if networks is not None
                    else load_selector(model_bytes(config, "selector")))
        return selector_presmoothed(mesh, selector, config.bounded_noise, device)

    def done(stage: str) -> None:
        if progress is not None:
            progress(STAGE_PROGRESS[stage])

    # The light remesh's kernel children start now: their interpreters start and import
    # while the stages before the remesh run.
    pieces = kernel_piece_count(mesh.face_count, None) if config.remesh_iterations > 0 else 0
    with kernel_children(pieces) as children:
        return _enhanced_by_views(mesh, config, device, done, children, networks)


def _enhanced_by_views(mesh: TriangleMesh, config: EnhanceConfig, device: str,
                       done: Callable[[str], None], children: Sequence[KernelChild],
                       networks: EnhanceNetworks | None) -> TriangleMesh:
    """`enhance_mesh` of the view-based methods, the light remesh's kernel in `children`,
    the `networks` given (None: loaded as their stages begin)."""
    from pipeline.enhance.device import accelerator

    # The stages gather neighbours all over the mesh; in a spatial order they hit the cache.
    order = spatial_order(mesh)
    ordered = reordered(mesh, order)
    # The noise gate (numpy) runs beside the render (open3d), both free of the GIL in their
    # loops. Loading the networks beside the pre-smoothing was slower on 2 cores: two
    # threads' torch ops each ask for every core (bunny 5.2-6.2 s against 4.9-5.1 s).
    ahead = config.remesh_iterations > 0 and remeshes_ahead(config)
    with ThreadPoolExecutor(max_workers=1) as pool:
        gate = pool.submit(skips_enhancement, mesh, config, device)
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
    if config.remesh_iterations == 0:  # the output keeps the input's order
        return restored(_updated(ordered, inputs, config, device, done, networks), order)
    result = (_updated_remeshed_ahead(ordered, inputs, config, device, done, children,
                                      checked.result() if checked is not None else None,
                                      networks)
              if ahead else
              light_remesh(_updated(ordered, inputs, config, device, done, networks),
                           config.remesh_iterations, children))
    done("remesh")
    return result


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
    thread: on a GPU the host has little else to do."""
    def start() -> RemeshAhead | None:
        remesh_config = light_remesh_config(inputs.base, config.remesh_iterations)
        return start_remesh_ahead(inputs.base, remesh_config, children, checked)

    with ThreadPoolExecutor(max_workers=1) as pool:
        starting = pool.submit(start)
        result = _updated(ordered, inputs, config, device, done, networks)
        ahead = starting.result()
    if ahead is None:  # the repair dropped vertices: remesh the moved mesh
        return light_remesh(result, config.remesh_iterations, children)
    return finish_remesh_ahead(ahead, result)[0]


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
    from pipeline.enhance.inference import load_selector, model_bytes, presmoothed

    if renders is None:
        renders = render_depth(mesh, views_for(mesh, config), with_color=True,
                               device=accelerator(device))
    views = renders.views
    done("render")
    base, base_renders, update = mesh, renders, config.update
    if config.method != "views" and config.presmooth_iterations > 0:
        selector = None
        if config.presmooth_learned:
            selector = (networks.selector if networks is not None
                        else load_selector(model_bytes(config, "selector")))
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
    `device`: `model`, loaded beforehand (`inference.load_vertex_gain`), else loaded here."""
    from pipeline.enhance.inference import load_vertex_gain, model_bytes, vertex_gains
    from pipeline.enhance.vertex_gain import gain_features

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

    return noise_to_edge_ratio(mesh, accelerator(device)) < config.min_noise_ratio


def gated(config: EnhanceConfig) -> bool:
    """Whether `config`'s method leaves a mesh less noisy than `min_noise_ratio` as it is."""
    return config.method in ("ldm", "regressor") and config.min_noise_ratio > 0


LIGHT_REMESH_MAX_ADDED_OUTSIDE = 2e-4
"""The light remesh's kernel is dropped where it adds more than this share of faces outside
the angle criteria. Under the benchmark's protocol as it was before long boundary edges were
split it added 0.14 % (suzanne) and 0.16 % (beetle), where it did harm; 0.002 % (cheburashka,
a few faces) or none, where it helped. Under the protocol now it keeps the kernel on suzanne,
where it does harm (1.0123 -> 1.0265 mm); not re-tuned on the benchmark's meshes:
`LIGHT_REMESH_MAX_LOST_EDGES` drops it there."""

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
    (`benchmarks/remesh_speed.py`)."""
    return remesh(mesh, light_remesh_config(mesh, iterations), children)[0]


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
    (`inference.load_enhancer`; None: loaded here)."""
    if config.method == "views":
        return base.depth_n
    from pipeline.enhance.inference import run_network

    predicted = run_network(base, noisy, config, enhancer)
    return base.depth_n + config.correction_gain * (predicted - base.depth_n)
