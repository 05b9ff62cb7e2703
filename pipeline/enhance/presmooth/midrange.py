"""Bounded vertex noise: the middle of each neighbourhood's residual range (the midrange
estimator), the pre-smoothing's last step.

Where the vertex noise along the normals is uniform in ±a (the vertex noise of the training
data), a smooth estimate's residual at a vertex, the noisy vertex's offset from it along its
normal, is the noise minus the estimate's own error r there. Over a neighbourhood of n
vertices in which r hardly varies, the residuals fill [-a - r, a - r], so the middle of their
range, (max + min) / 2, estimates -r with an error that falls as 1/n: it is the best unbiased
estimate of a uniform's centre. A linear smoother (Laplacian smoothing, twicing, the
selector's blend of twicings) averages, and an average's error falls only as 1/sqrt(n). The
range is a poor estimate where the noise has tails (Gaussian noise: kurtosis 3, the
uniform's is 1.8), so the refinement runs only on a mesh whose residuals are light-tailed
(Hogg's adaptive choice of a location estimator by the sample's tails); otherwise the smooth
estimate is returned as it is.

The refinement runs in numpy and scipy on the host (`midrange_numpy`, device None) or in torch
on a device (`midrange_torch`); both share `midrange_common`, and neither imports the other.
"""

from __future__ import annotations

from pipeline.enhance.presmooth import midrange_numpy
from pipeline.enhance.presmooth.midrange_common import BoundedNoiseConfig, residual_kurtosis
from pipeline.geometry.mesh import TriangleMesh

__all__ = ["BoundedNoiseConfig", "bounded_noise_refine", "refined_where_bounded",
           "residual_kurtosis"]


def bounded_noise_refine(noisy: TriangleMesh, smooth: TriangleMesh,
                         config: BoundedNoiseConfig, device: str | None = None) -> TriangleMesh:
    """`smooth` (a smoothing of `noisy`, the same faces) with each vertex moved along its normal
    by the middle of the residual range of its neighbourhood; `smooth` itself where
    `config.rings` is 0 or the residuals are not light-tailed (`residual_kurtosis`). In torch
    on `device` where given, else in numpy and scipy."""
    refined = refined_where_bounded(noisy, smooth, config, device)
    return smooth if refined is None else refined


def refined_where_bounded(noisy: TriangleMesh, smooth: TriangleMesh,
                          config: BoundedNoiseConfig, device: str | None = None
                          ) -> TriangleMesh | None:
    """`bounded_noise_refine`'s mesh where the refinement runs, None where it does not."""
    if config.rings == 0:
        return None
    if device is None:
        return midrange_numpy.refined(noisy, smooth, config)
    from pipeline.enhance.presmooth import midrange_torch

    return midrange_torch.refined(noisy, smooth, config, device)
