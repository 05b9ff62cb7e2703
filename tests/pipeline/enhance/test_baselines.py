import numpy as np
import pytest

from pipeline.enhance.baselines import bilateral_denoise, laplacian_smooth, taubin_smooth


def _radial_std(mesh) -> float:
    return float(np.linalg.norm(mesh.vertices_m, axis=1).std())


@pytest.mark.parametrize(
    ("smoother", "ratio"),
    # Bilateral denoising moves least per iteration (it preserves features by design).
    [(laplacian_smooth, 0.6), (taubin_smooth, 0.6), (bilateral_denoise, 0.85)],
    ids=["laplacian", "taubin", "bilateral"],
)
def test_smoothers_reduce_noise_and_keep_connectivity(noisy_sphere, smoother, ratio):
    _, noisy = noisy_sphere
    out = smoother(noisy, 3)
    # Spread of radii (shrinkage aside, which a coarse sphere shows strongly).
    assert _radial_std(out) < ratio * _radial_std(noisy)
    assert np.array_equal(out.faces, noisy.faces)


def test_zero_iterations_is_identity_and_negative_is_rejected(noisy_sphere):
    _, noisy = noisy_sphere
    assert np.array_equal(laplacian_smooth(noisy, 0).vertices_m, noisy.vertices_m)
    with pytest.raises(ValueError, match="iterations"):
        taubin_smooth(noisy, -1)


def test_taubin_shrinks_less_than_laplacian(unit_sphere):
    lap = laplacian_smooth(unit_sphere, 20)
    tau = taubin_smooth(unit_sphere, 20)
    r_lap = np.linalg.norm(lap.vertices_m, axis=1).mean()
    r_tau = np.linalg.norm(tau.vertices_m, axis=1).mean()
    assert abs(r_tau - 0.5) < abs(r_lap - 0.5)
