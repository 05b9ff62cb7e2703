"""Running loaded networks (`loading`): the per-vertex networks in row chunks, the selector's
pre-smoothing (scale selection, then the midrange estimator), and the depth networks on a
batch of renders."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.render.views import DepthRenders, canny_edges
from pipeline.enhance.weights.loading import load_enhancer
from pipeline.geometry.mesh import TriangleMesh

if TYPE_CHECKING:
    import torch

    from pipeline.enhance.config import EnhanceConfig
    from pipeline.enhance.presmooth.midrange import BoundedNoiseConfig
    from pipeline.enhance.presmooth.scale_selection import TwicingCandidates


ROW_CHUNK = 4096
"""Rows a per-vertex network takes at a time on the CPU (`by_row_chunks`): its activations
then stay in the cache."""


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
    from pipeline.enhance.presmooth.scale_selection import blend

    return blend(candidates.vertices_m, by_row_chunks(model, candidates.features, device))


def selector_presmoothed(mesh: TriangleMesh, selector, bounded: BoundedNoiseConfig | None,
                         device: str | None = None) -> TriangleMesh:
    """The pre-smoothing of every method: a loaded selector's (`load_selector`) blend of the
    mesh's twicings (scale selection), then the midrange estimator of `bounded` where given
    and where it runs (`refined_where_bounded`). The smoothing steps run on `device` (None:
    scipy)."""
    from pipeline.enhance.device import accelerator
    from pipeline.enhance.presmooth.midrange import refined_where_bounded
    from pipeline.enhance.presmooth.scale_selection import blend, twicing_candidates

    candidates = twicing_candidates(mesh, selector.config.blend, device)
    weights = by_row_chunks(selector, candidates.features, device or "cpu")
    blended = mesh.with_vertices(blend(candidates.vertices_m, weights))
    if bounded is None:
        return blended
    refined = refined_where_bounded(mesh, blended, bounded, accelerator(device))
    return blended if refined is None else refined


Network = Callable[["torch.Tensor", "torch.Tensor", "torch.Tensor"], "torch.Tensor"]
"""A loaded network on its device: (N, 1, H, W) depth, validity and side inputs to the
enhanced depth (`as_network`)."""


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
    the mesh as it came, from the same views (their colour gives the edge input)."""
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
    with torch.no_grad():
        enhanced = net(d, v, side)[:, 0].cpu().numpy().astype(np.float32)
    return np.where(base.valid, enhanced, base.depth_n)
