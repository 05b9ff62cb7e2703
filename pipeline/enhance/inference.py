"""Loading trained networks from safetensors bytes and running them on a batch of renders."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.render import DepthRenders, canny_edges
from pipeline.mesh import TriangleMesh

if TYPE_CHECKING:
    import torch

    from pipeline.enhance.bounded_noise import BoundedNoiseConfig
    from pipeline.enhance.config import EnhanceConfig
    from pipeline.enhance.twicing_blend import TwicingCandidates


def weights_to_bytes(state: dict[str, torch.Tensor], config: dict, half: bool = False) -> bytes:
    """safetensors bytes of a state dict, with its model config as JSON metadata; `half`
    stores float tensors as float16 (shipped weights: half the size, loaded back as float32)."""
    from safetensors.torch import save

    tensors = {k: v.detach().cpu().contiguous() for k, v in state.items()}
    if half:
        tensors = {k: v.half() if v.is_floating_point() else v for k, v in tensors.items()}
    return save(tensors, metadata={"config": json.dumps(config)})


SAFETENSORS_DTYPES = {"F16": "float16", "BF16": "bfloat16", "F32": "float32", "F64": "float64",
                      "I64": "int64", "I32": "int32", "I16": "int16", "I8": "int8", "U8": "uint8",
                      "BOOL": "bool"}
"""The safetensors dtype names `weights_from_bytes` reads, as torch's."""


def weights_from_bytes(data: bytes, device: str | torch.device = "cpu"
                       ) -> tuple[dict[str, torch.Tensor], dict]:
    """(state dict on `device`, model config) from safetensors bytes, floating tensors in
    float32.

    The file's tensor bytes go to `device` in one copy and each dtype's tensors are converted
    there in one op, then handed out as views. Loaded on the CPU and then moved, torch's CPU
    ops on the weights (a cat and a conversion, parallel on every core) waited on the cores
    of the light remesh's children, starting beside them. On one H100 machine the networks'
    stage took 0.57-0.59 s that way and 0.24-0.37 s loaded this way, with the children both
    times; 0.23-0.24 s with none (README, the H100 section)."""
    import torch

    header_len = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + header_len])
    config = json.loads(header.pop("__metadata__", {}).get("config", "{}"))
    # One copy, writable for torch (a bytes slice first copied it twice: 13 ms, not 0.5 ms,
    # for the LDM's file).
    raw = torch.frombuffer(bytearray(memoryview(data)[8 + header_len :]),
                           dtype=torch.uint8).to(device)
    state: dict[str, torch.Tensor] = {}
    for name in {entry["dtype"] for entry in header.values()}:
        dtype = getattr(torch, SAFETENSORS_DTYPES[name])
        entries = sorted(((v["data_offsets"], k, v["shape"]) for k, v in header.items()
                          if v["dtype"] == name))
        # Tensors of one dtype lie together in the files safetensors writes; their span's
        # stray bytes, if any, are converted too and never read.
        start, end = entries[0][0][0], entries[-1][0][1]
        span = raw[start:end].view(dtype)
        if span.is_floating_point():
            span = span.float()
        bounds = [(offset - start) // dtype.itemsize for offsets, _, _ in entries
                  for offset in offsets]
        # Cut at every tensor's first and last element: the odd parts are the tensors.
        parts = span.tensor_split(bounds)[1::2]
        for (_, k, shape), part in zip(entries, parts, strict=True):
            state[k] = part.view(shape)
    return state, config


def _tuples(d: dict) -> dict:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}


Module = TypeVar("Module", bound="torch.nn.Module")


def _with_weights(make: Callable[[], Module], state: dict[str, torch.Tensor]) -> Module:
    """The module `make` builds, its parameters and buffers `state`'s tensors themselves, in
    eval mode. Built on the meta device, so no initial weights are drawn only to be
    overwritten (the LDM's networks: most of their load time)."""
    import torch

    with torch.device("meta"):
        module = make()
    module.load_state_dict(state, assign=True)  # strict: every tensor must be in `state`
    return module.eval()


def load_regressor(data: bytes, device: str | torch.device = "cpu"):
    """A `ResidualUNet`, or a `RefinedRegressor` where the metadata names the regressor it
    refines (`regressor_to_bytes`), its weights on `device`."""
    from pipeline.enhance.models.regressor import RefinedRegressor, RegressorConfig, ResidualUNet

    state, cfg = weights_from_bytes(data, device)
    refines_cfg = cfg.pop("refines_regressor", None)
    def make():
        second = ResidualUNet(RegressorConfig(**_tuples(cfg)))
        return second if refines_cfg is None else RefinedRegressor(
            ResidualUNet(RegressorConfig(**_tuples(refines_cfg))), second)

    return _with_weights(make, state)


def regressor_to_bytes(model, half: bool = False) -> bytes:
    """safetensors bytes of a `ResidualUNet` or a `RefinedRegressor` (with the regressor it
    refines, so the two cannot be mismatched), its config as metadata."""
    from dataclasses import asdict

    from pipeline.enhance.models.regressor import RefinedRegressor

    if isinstance(model, RefinedRegressor):
        meta = {**asdict(model.second.config), "refines_regressor": asdict(model.first.config)}
    else:
        meta = asdict(model.config)
    return weights_to_bytes(model.state_dict(), meta, half)


def load_vae(data: bytes, device: str | torch.device = "cpu"):
    from pipeline.enhance.models.vae import DepthVAE, VAEConfig

    state, cfg = weights_from_bytes(data, device)
    return _with_weights(lambda: DepthVAE(VAEConfig(**_tuples(cfg))), state)


def load_ldm(vae_data: bytes, ldm_data: bytes, device: str | torch.device = "cpu"):
    """`LDMModels` from the VAE's and the LDM's bytes, their weights on `device`; an LDM
    trained to refine a regressor carries that regressor's weights (`ldm_to_bytes`), so the
    two cannot be mismatched."""
    from pipeline.enhance.models.controlnet import ControlNet
    from pipeline.enhance.models.regressor import RegressorConfig, ResidualUNet
    from pipeline.enhance.models.unet import LatentUNet, UNetConfig
    from pipeline.enhance.pipelines.depth_ldm import LDMModels

    vae = load_vae(vae_data, device)
    ldm_state, meta = weights_from_bytes(ldm_data, device)
    refines_cfg = meta.pop("refines_regressor", None)
    cfg = UNetConfig(**_tuples(meta))
    unet = _with_weights(lambda: LatentUNet(cfg), _prefixed(ldm_state, "unet."))
    control = _with_weights(lambda: ControlNet(cfg), _prefixed(ldm_state, "controlnet."))
    refines = None
    if refines_cfg is not None:
        refines = _with_weights(lambda: ResidualUNet(RegressorConfig(**_tuples(refines_cfg))),
                                _prefixed(ldm_state, "refines."))
    return LDMModels(vae, unet, control, refines)


def ldm_to_bytes(models, unet_config: dict, half: bool = False) -> bytes:
    """safetensors bytes of an `LDMModels`' U-Net and ControlNet, and of the regressor it
    refines; the VAE is stored apart."""
    from dataclasses import asdict

    parts = {"unet": models.unet, "controlnet": models.controlnet}
    meta = dict(unet_config)
    if models.refines is not None:
        parts["refines"] = models.refines
        meta["refines_regressor"] = asdict(models.refines.config)
    state = {f"{name}.{k}": v for name, part in parts.items() for k, v in part.state_dict().items()}
    return weights_to_bytes(state, meta, half)


def _prefixed(state: dict, prefix: str) -> dict:
    return {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}


def load_selector(data: bytes):
    """A `TwicingSelector`, or a `SelectorEnsemble` where the metadata lists its members
    (`selector_ensemble_to_bytes`)."""
    from pipeline.enhance.models.twicing_selector import (
        SelectorConfig,
        SelectorEnsemble,
        TwicingSelector,
    )

    state, cfg = weights_from_bytes(data)
    cfg.pop("member_sha256", None)
    def make():
        members = [TwicingSelector(SelectorConfig(**_tuples(c)))
                   for c in cfg.get("members", [cfg])]
        return members[0] if "members" not in cfg else SelectorEnsemble(members)

    return _with_weights(make, state)


def selector_ensemble_to_bytes(selectors: list[bytes], half: bool = False) -> bytes:
    """safetensors bytes of the `SelectorEnsemble` of selectors' safetensors bytes, each
    member's config and the SHA-256 of its bytes in the metadata."""
    import hashlib
    from dataclasses import asdict

    from pipeline.enhance.models.twicing_selector import SelectorEnsemble

    members = [load_selector(data) for data in selectors]
    if any(isinstance(m, SelectorEnsemble) for m in members):
        raise ValueError("selector-ensemble: a member is itself an ensemble")
    meta = {"members": [asdict(m.config) for m in members],
            "member_sha256": [hashlib.sha256(data).hexdigest() for data in selectors]}
    return weights_to_bytes(SelectorEnsemble(members).state_dict(), meta, half)


def interpolated_weights(start: bytes, end: bytes, share_of_end: float) -> bytes:
    """safetensors bytes (float16, as shipped) of the network whose every floating tensor is
    (1 - share_of_end) * start's + share_of_end * end's: the weight-space average of a
    fine-tuned network and the one it was fine-tuned from (WiSE-FT, Wortsman et al. 2022),
    which keeps more of the earlier network's behaviour on data unlike the fine-tuning's.
    Both must hold the same network (the same config and tensors)."""
    start_state, start_config = weights_from_bytes(start)
    end_state, end_config = weights_from_bytes(end)
    if start_config != end_config or start_state.keys() != end_state.keys() or any(
            start_state[k].shape != end_state[k].shape for k in end_state):
        raise ValueError("the two files hold different networks")
    state = {k: v.lerp(end_state[k], share_of_end) if v.is_floating_point() else end_state[k]
             for k, v in start_state.items()}
    return weights_to_bytes(state, end_config, half=True)


def load_vertex_gain(data: bytes):
    from pipeline.enhance.models.vertex_gain import VertexGainConfig, VertexGainNet

    state, cfg = weights_from_bytes(data)
    return _with_weights(lambda: VertexGainNet(VertexGainConfig(**cfg)), state)


ROW_CHUNK = 4096
"""Rows a per-vertex network takes at a time (`by_row_chunks`): its activations then stay in
the cache. The selector ensemble on beetle's 258 k rows, 2 cores: 2.6 s in one batch, 2.0 s
in chunks of 64 k rows, 1.1 s of 8 k, 1.0 s of 4 k."""


def by_row_chunks(model, rows: NDArray[np.float32], device: str = "cpu") -> NDArray[np.float32]:
    """(V, ...) a per-row network's outputs for (V, F) rows, the network moved to `device`:
    on the CPU `ROW_CHUNK` rows at a time (no rows: one empty chunk), on a GPU in one batch,
    where the chunks' launches would cost more than the cache saves."""
    import torch

    chunk = ROW_CHUNK if device == "cpu" else max(len(rows), 1)
    model.to(device)
    with torch.no_grad():
        rows_t = torch.from_numpy(rows).to(device)
        return torch.cat([model(rows_t[i:i + chunk])
                          for i in range(0, max(len(rows), 1), chunk)]).cpu().numpy()


def vertex_gains(model, features: NDArray[np.float32], device: str = "cpu"
                 ) -> NDArray[np.float64]:
    """(V,) a loaded `VertexGainNet`'s gains for (V, F) `vertex_gain.gain_features`, run on
    `device`."""
    return by_row_chunks(model, features, device).astype(np.float64)


def selector_blend(model, candidates: TwicingCandidates, device: str = "cpu"
                   ) -> NDArray[np.float64]:
    """(V, 3) the candidates blended with a loaded `TwicingSelector`'s weights, run on
    `device`."""
    from pipeline.enhance.twicing_blend import blend

    return blend(candidates.vertices_m, by_row_chunks(model, candidates.features, device))


def presmoothed(
    mesh: TriangleMesh, iterations: int, passes: int, adaptive: bool, selector=None,
    device: str | None = None, bounded: BoundedNoiseConfig | None = None,
) -> TriangleMesh:
    """The networks' pre-smoothing, for inference and training pairs alike: the blend of a
    loaded `selector` (`load_selector`) where one is given (its smoothing on `device`), else
    `baselines.presmooth`, then `bounded`'s refinement where given
    (`bounded_noise_refine`); 0 iterations: the mesh."""
    from pipeline.enhance.baselines import presmooth
    from pipeline.enhance.bounded_noise import bounded_noise_refine
    from pipeline.enhance.device import accelerator

    if iterations == 0:
        return mesh
    if selector is not None:
        return selector_presmoothed(mesh, selector, bounded, device)
    smooth = presmooth(mesh, iterations, passes, adaptive)
    if bounded is None:
        return smooth
    return bounded_noise_refine(mesh, smooth, bounded, accelerator(device))


def selector_presmoothed(mesh: TriangleMesh, selector, bounded: BoundedNoiseConfig | None,
                         device: str | None = None) -> TriangleMesh:
    """A loaded selector's (`load_selector`) blend of the mesh's twicings, then `bounded`'s
    refinement where given and where it runs (`refined_where_bounded`): from the blend of
    the weights averaged over the neighbours (`BoundedNoiseConfig.weight_passes`); where it
    does not run, the blend as it is. The smoothing steps run on `device` (None: scipy)."""
    from pipeline.enhance.bounded_noise import refined_where_bounded
    from pipeline.enhance.device import accelerator
    from pipeline.enhance.twicing_blend import blend, twicing_candidates, weights_averaged

    candidates = twicing_candidates(mesh, selector.config.blend, device)
    weights = by_row_chunks(selector, candidates.features, device or "cpu")

    def blended(rows: NDArray[np.float32]) -> TriangleMesh:
        return mesh.with_vertices(blend(candidates.vertices_m, rows))

    if bounded is None:
        return blended(weights)
    base = blended(weights_averaged(candidates, weights, bounded.weight_passes))
    refined = refined_where_bounded(mesh, base, bounded, accelerator(device))
    return blended(weights) if refined is None else refined


def model_bytes(config: EnhanceConfig, name: str) -> bytes:
    """The safetensors bytes of model `name`: `config.weights`' if given, else the shipped."""
    from pipeline.enhance.weights import shipped_bytes

    if config.weights is not None and name in config.weights:
        return config.weights[name]
    return shipped_bytes(name)


def dihedral(x, k: int, inverse: bool = False):
    """The k-th of the 8 flips/transposes of (..., H, W) square images (k = 0: identity)."""
    if inverse:
        if k & 4:
            x = x.transpose(-1, -2)
        if k & 2:
            x = x.flip(-2)
        if k & 1:
            x = x.flip(-1)
        return x
    if k & 1:
        x = x.flip(-1)
    if k & 2:
        x = x.flip(-2)
    if k & 4:
        x = x.transpose(-1, -2)
    return x


Network = Callable[["torch.Tensor", "torch.Tensor", "torch.Tensor"], "torch.Tensor"]
"""A loaded network on its device: (N, 1, H, W) depth, validity and side inputs to the
enhanced depth (`as_network`)."""


def load_enhancer(config: EnhanceConfig):
    """`config.method`'s depth network (the regressor, or the LDM's `LDMModels`), loaded
    and moved to `config.device`; on the CPU its weights in channels-last order, where
    oneDNN's convolutions run quicker (the bunny's 6 views through the LDM on 2 cores
    2.09-2.26 -> 1.66-1.83 s, the output within 3.4e-6 of normalised depth). Not measured
    on a GPU, so left as it was there."""
    import torch

    from pipeline.enhance.device import resolve_device

    device = resolve_device(config.device)
    layout = torch.channels_last if device.type == "cpu" else torch.contiguous_format
    if config.method == "regressor":
        return load_regressor(model_bytes(config, "regressor"), device).to(
            device, memory_format=layout)
    if config.method == "ldm":
        models = load_ldm(model_bytes(config, "vae"), model_bytes(config, "ldm"), device)
        for part in (models.vae, models.unet, models.controlnet, models.refines):
            if part is not None:
                part.to(device, memory_format=layout)
        return models
    raise ValueError(f"method: {config.method!r} has no network")


def as_network(enhancer, config: EnhanceConfig) -> Network:
    """A loaded depth network (`load_enhancer`) as a `Network`, with `config`'s sampling
    settings for the LDM."""
    from pipeline.enhance.pipelines.depth_ldm import LDMModels, enhance_depth_ldm

    if not isinstance(enhancer, LDMModels):
        return enhancer

    def ldm(d, v, e):
        return enhance_depth_ldm(enhancer, d, v, config.steps, config.strength, config.seed, e)
    return ldm


def run_network(
    base: DepthRenders, noisy: DepthRenders, config: EnhanceConfig, enhancer=None
) -> NDArray[np.float32]:
    """(N, H, W) enhanced normalised depth from the chosen network: `enhancer`, loaded
    beforehand for `config` (`load_enhancer`), else loaded here; invalid pixels unchanged.

    `base` are the renders the network corrects (of the pre-smoothed mesh), `noisy` those of
    the mesh as it came, from the same views (their colour gives the edge input).

    With `config.ensemble` > 1 the views are also enhanced flipped and transposed, and the
    results averaged: the networks' errors differ between those copies while the surface
    does not (the geometric self-ensemble of super-resolution work).
    """
    import torch

    from pipeline.enhance.device import resolve_device
    from pipeline.enhance.models.common import side_inputs

    net = as_network(load_enhancer(config) if enhancer is None else enhancer, config)
    device = resolve_device(config.device)
    d = torch.from_numpy(base.depth_n[:, None]).to(device)
    v = torch.from_numpy(base.valid[:, None]).to(device)
    edges_np = canny_edges(noisy.color_rgb, noisy.valid)
    e = None if edges_np is None else torch.from_numpy(edges_np[:, None]).to(device)
    side = side_inputs(e, torch.from_numpy(noisy.depth_n[:, None]).to(device), d, v)
    total = torch.zeros_like(d)
    with torch.no_grad():
        for k in range(config.ensemble):
            t = [dihedral(x, k) for x in (d, v, side)]
            total += dihedral(net(*t), k, inverse=True)
    enhanced = (total / config.ensemble)[:, 0].cpu().numpy().astype(np.float32)
    return np.where(base.valid, enhanced, base.depth_n)
