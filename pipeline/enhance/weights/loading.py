"""Networks to and from safetensors bytes: the state dicts' bytes, each model's loader (built
on the meta device, its weights the file's own tensors) and the bytes a config names."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    import torch

    from pipeline.enhance.config import EnhanceConfig


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
    there in one op, then handed out as views: loaded on the CPU and then moved, torch's CPU
    ops on the weights (parallel on every core) would wait on the cores of the light
    remesh's children, starting beside them."""
    import torch

    header_len = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + header_len])
    config = json.loads(header.pop("__metadata__", {}).get("config", "{}"))
    # One copy, writable for torch (a bytes slice would copy it twice).
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
    """A `ResidualUNet`, its weights on `device`."""
    from pipeline.enhance.models.regressor import RegressorConfig, ResidualUNet

    state, cfg = weights_from_bytes(data, device)
    return _with_weights(lambda: ResidualUNet(RegressorConfig(**_tuples(cfg))), state)


def regressor_to_bytes(model, half: bool = False) -> bytes:
    """safetensors bytes of a `ResidualUNet`, its config as metadata."""
    from dataclasses import asdict

    return weights_to_bytes(model.state_dict(), asdict(model.config), half)


def load_vae(data: bytes, device: str | torch.device = "cpu"):
    """A `DepthVAE`, its weights on `device`."""
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
        raise ValueError("--selector-ensemble: a member is itself an ensemble")
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


def model_bytes(config: EnhanceConfig, name: str) -> bytes:
    """The safetensors bytes of model `name`: `config.weights`' if given, else the shipped."""
    from pipeline.enhance.weights import shipped_bytes

    if config.weights is not None and name in config.weights:
        return config.weights[name]
    return shipped_bytes(name)


def load_enhancer(config: EnhanceConfig):
    """`config.method`'s depth network (the regressor, or the LDM's `LDMModels`), loaded
    and moved to `config.device`; on the CPU its weights in channels-last order, where
    oneDNN's convolutions run quicker (on a GPU in torch's default layout)."""
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
