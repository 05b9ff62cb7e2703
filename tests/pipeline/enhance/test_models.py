import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.models.common import depth_features, side_inputs
from pipeline.enhance.models.controlnet import ControlNet
from pipeline.enhance.models.regressor import RegressorConfig, ResidualUNet
from pipeline.enhance.models.unet import LatentUNet, UNetConfig
from pipeline.enhance.models.vae import DepthVAE, VAEConfig

UNET = UNetConfig(channels=(16, 16), emb_dim=32)


def _depth(b=2, h=32, w=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = 0.4 + 0.05 * torch.rand(b, 1, h, w, generator=g)
    v = torch.ones_like(d, dtype=torch.bool)
    v[..., :4] = False
    return torch.where(v, d, torch.ones_like(d)), v


@settings(max_examples=10, deadline=None)
@given(st.floats(-0.3, 0.3))
def test_features_do_not_depend_on_absolute_depth(shift):
    d, v = _depth()
    a = depth_features(d, v)
    b = depth_features(torch.where(v, d + shift, d), v)
    assert torch.allclose(a, b, atol=1e-4)


@settings(max_examples=10, deadline=None)
@given(st.floats(-0.3, 0.3), st.floats(-0.02, 0.02))
def test_side_inputs_read_only_the_noisy_renders_offset_from_the_base(shift, offset):
    """A shift of both renders changes nothing; the noisy render's offset from the base is
    what the detail channel carries, zero where the noisy render has no surface."""
    d, v = _depth()
    noisy = torch.where(v, d + offset, d)
    noisy[..., 6:8] = 1.0  # a hole in the noisy render only
    a = depth_features(d, v, side_inputs(None, noisy, d, v))
    moved = torch.where(v, d + shift, d)
    b = depth_features(moved, v, side_inputs(None, torch.where(noisy < 1, noisy + shift, 1.0),
                                             moved, v))
    assert torch.allclose(a, b, atol=1e-3)
    detail = a[:, 5]
    assert torch.allclose(detail[..., 8:], torch.full_like(detail[..., 8:], offset * 100.0)
                          .clamp(-3, 3), atol=1e-3)
    assert float(detail[..., :4].abs().max()) == 0.0  # no base surface
    assert float(detail[..., 6:8].abs().max()) == 0.0  # no noisy surface


def test_vae_latent_is_four_channels_at_one_eighth():
    d, v = _depth(h=40, w=48)
    vae = DepthVAE(VAEConfig(channels=(8, 8, 16, 16)))
    post = vae.encode(d, v)
    assert post.mean.shape == (2, 4, 5, 6)
    assert post.kl().shape == (2,)
    out = vae.decode(post.sample(), d, v)
    assert out.shape == d.shape


@settings(max_examples=8, deadline=None)
@given(st.floats(-0.2, 0.2))
def test_vae_latent_reads_local_shape_not_the_depth_offset(shift):
    """The encoder reads only local shape: a depth shifted as a whole leaves the latent as it
    is (the guide of the decoder gives its place)."""
    d, v = _depth()
    torch.manual_seed(0)
    vae = DepthVAE(VAEConfig(channels=(8, 8, 16, 16)))
    moved = torch.where(v, d + shift, d)
    assert torch.allclose(vae.encode(moved, v).mean, vae.encode(d, v).mean, atol=1e-4)


def test_the_shipped_vae_loads_and_names_only_settings_the_model_has():
    from dataclasses import fields

    from pipeline.enhance.models.vae import VAEConfig
    from pipeline.enhance.weights import shipped_bytes
    from pipeline.enhance.weights.loading import load_vae, weights_from_bytes, weights_to_bytes

    shipped = shipped_bytes("vae")
    state, config = weights_from_bytes(shipped)
    assert set(config) == {f.name for f in fields(VAEConfig)}
    assert isinstance(load_vae(shipped), DepthVAE)
    with pytest.raises(TypeError, match="encode_correction"):
        load_vae(weights_to_bytes(state, {**config, "encode_correction": True}))


def test_controlnet_starts_as_a_no_op():
    torch.manual_seed(0)
    unet, control = LatentUNet(UNET), ControlNet(UNET)
    control.copy_encoder_from(unet)
    d, v = _depth()
    z = torch.randn(2, 4, 4, 4)
    t = torch.tensor([10, 500])
    residuals = control(z, t, control.hint_of(d, v))
    assert len(residuals) == len(UNET.channels) + 1
    assert all(float(r.detach().abs().max()) == 0.0 for r in residuals)
    assert torch.equal(unet(z, t, residuals), unet(z, t))
    # The timestep changes the output (the embedding is wired in).
    assert not torch.allclose(unet(z, t), unet(z, t.flip(0)))


def test_regressor_is_fully_convolutional_and_residual():
    model = ResidualUNet(RegressorConfig(channels=(8, 16)))
    torch.nn.init.zeros_(model.conv_out.weight)
    torch.nn.init.zeros_(model.conv_out.bias)
    d, v = _depth(h=30, w=34)
    assert torch.equal(model(d, v), d)


def test_vae_posterior_starts_narrow():
    """A small starting variance keeps early latents informative (against posterior collapse)."""
    d, v = _depth()
    post = DepthVAE(VAEConfig(channels=(8, 8, 16, 16), initial_logvar=-6.0)).encode(d, v)
    assert float(post.logvar.mean().detach()) < -4.0
