"""The bounded-noise refinement's settings and its tail test: what both implementations of the
midrange estimator (`midrange_numpy` on the host, `midrange_torch` on a device) share."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BoundedNoiseConfig:
    """The neighbourhood and the tail test of `midrange.bounded_noise_refine`."""

    rings: int = 3
    """Rings of neighbours whose residual range a vertex takes the middle of; 0: off. Fewer
    leave more noise (the range of a few residuals), more bend the range over curved parts."""
    smoothing: int = 2
    """Passes of neighbour averaging (the vertex among its neighbours) of the range's middle."""
    max_kurtosis: float = 2.4
    """The refinement runs only where the residuals' kurtosis is below this: halfway between
    uniform noise's 1.8 and Gaussian noise's 3."""


def residual_kurtosis(residual_m) -> float:
    """The (V,) residuals' kurtosis, E[(x - mean)^4] / var^2: 1.8 for uniform noise, 3 for
    Gaussian, more for noise with outliers (inf for residuals that are all alike); numpy or
    torch."""
    centred = residual_m - residual_m.mean()
    variance = float((centred**2).mean())
    if variance == 0.0:
        return float("inf")
    return float((centred**4).mean()) / variance**2
