"""Weights made from trained weights rather than by training: the weight-space average of a
fine-tuning run with its start (WiSE-FT) and the ensemble of selectors trained with
different seeds. The shipped weights' recipe uses both (MODEL_CARD.md)."""

from __future__ import annotations

from collections.abc import Sequence

from pipeline.enhance.training.plan import DEPTH_NETWORKS, WeightsStore


def averaged_weights(start: WeightsStore, end: WeightsStore, share_of_end: float
                     ) -> dict[str, bytes]:
    """The files of a weights folder whose depth networks (regressor, VAE, LDM) lie
    `share_of_end` of the way from `start`'s to `end`'s, tensor by tensor (float16), with
    `end`'s other .safetensors (selector, vertex gains) as they are. ValueError names a
    missing or foreign file."""
    from pipeline.enhance.weights.loading import interpolated_weights

    for store in (start, end):
        missing = [n for n in DEPTH_NETWORKS if not store.has(f"{n}.safetensors")]
        if missing:
            raise ValueError(f"--average: {store.where} has no "
                             f"{', '.join(missing)}.safetensors")
    files = {n: end.read(n) for n in end.names() if n.endswith(".safetensors")}
    for name in DEPTH_NETWORKS:
        file = f"{name}.safetensors"
        try:
            files[file] = interpolated_weights(start.read(file), end.read(file), share_of_end)
        except Exception as exc:  # whatever a foreign file makes `weights_from_bytes` raise
            raise ValueError(f"--average: {file} of {start.where} and {end.where}: {exc}"
                             ) from None
    return files


def selector_ensemble(members: Sequence[tuple[str, bytes]]) -> bytes:
    """The selector.safetensors of the ensemble of (name, bytes) selectors: the mean of their
    blend weights. ValueError names a member that is no selector."""
    from pipeline.enhance.weights.loading import load_selector, selector_ensemble_to_bytes

    if len({name for name, _ in members}) < max(2, len(members)):
        raise ValueError("--selector-ensemble: give two or more different selector files")
    for name, data in members:
        try:
            load_selector(data)
        except Exception as exc:  # whatever a foreign file makes safetensors or torch raise
            raise ValueError(f"--selector-ensemble: {name} is not a selector file ({exc})"
                             ) from None
    return selector_ensemble_to_bytes([data for _, data in members])
