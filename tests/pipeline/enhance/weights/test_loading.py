"""Weights to and from safetensors bytes: every dtype back, as safetensors reads them, on any
device."""

import pytest
import torch

from pipeline.enhance.weights.loading import weights_from_bytes, weights_to_bytes


def _mixed_state() -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    return {"a.weight": torch.randn(5, 3, generator=g), "b.bias": torch.randn(7, generator=g),
            "steps": torch.arange(4, dtype=torch.int64), "scale": torch.tensor(2.5)}


@pytest.mark.parametrize("half", [False, True])
def test_weights_round_trip_with_every_dtype_in_float32(half):
    state = _mixed_state()
    loaded, config = weights_from_bytes(weights_to_bytes(state, {"width": 8}, half))
    assert config == {"width": 8}
    assert loaded.keys() == state.keys()
    for k, v in state.items():
        expected = v.half().float() if half and v.is_floating_point() else v
        assert loaded[k].dtype == (torch.float32 if v.is_floating_point() else v.dtype)
        assert loaded[k].shape == v.shape
        assert torch.equal(loaded[k], expected)


def test_weights_load_as_safetensors_reads_them():
    from safetensors.torch import load

    data = weights_to_bytes(_mixed_state(), {}, half=True)
    loaded, _ = weights_from_bytes(data)
    for k, v in load(data).items():
        assert torch.equal(loaded[k], v.float() if v.is_floating_point() else v)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_weights_load_on_cuda_as_on_the_cpu():
    data = weights_to_bytes(_mixed_state(), {}, half=True)
    on_cpu, _ = weights_from_bytes(data)
    on_cuda, _ = weights_from_bytes(data, "cuda")
    for k, v in on_cpu.items():
        assert on_cuda[k].device.type == "cuda"
        assert torch.equal(on_cuda[k].cpu(), v)
