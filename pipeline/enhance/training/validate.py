"""Validation figures on held-apart renders: depth RMSE overall and in a band at depth edges.

Figures are in thousandths of the view's depth range (a 1 m bunny's range is about 1.6 m, so
1.0 here is about 1.6 mm).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from numpy.typing import NDArray

from pipeline.enhance.metrics import depth_edge_band
from pipeline.enhance.models.common import side_inputs
from pipeline.enhance.models.regressor import ResidualUNet
from pipeline.enhance.models.vae import DepthVAE, padded
from pipeline.enhance.training.data import BULK_SURFACE_N, DepthPairs, same_surface_mask
from pipeline.enhance.update.steps import UpdateConfig

MIN_COS = UpdateConfig().min_cos


def _subset(pairs: DepthPairs, count: int) -> NDArray[np.int64]:
    n = len(pairs.source)
    return np.unique(np.linspace(0, n - 1, min(count, n)).round().astype(np.int64))


def depth_scores(pred: NDArray, pairs: DepthPairs, idx: NDArray[np.int64]) -> dict[str, float]:
    """RMSE, 3-pixel edge-band RMSE and normal RMSE (thousandths of depth range) of `pred`
    (n, H, W), and RMSE and normal RMSE on the bulk of the surface (`BULK_SURFACE_N`). The
    normal RMSE is the error as the mesh update sees it: each pixel's depth error times the
    cos of the clean surface's slant (its move along the normal), weighted by cos² as the
    update weighs views, over pixels slanted less than its visibility limit."""
    from pipeline.enhance.training.loop import slope_weights

    acc = {k: np.zeros(2) for k in ("all", "band", "normal", "bulk", "bulk_normal")}
    res = pairs.clean_n.shape[-1]
    for j, i in enumerate(idx):
        err = pred[j].astype(np.float64) - pairs.clean_n[i]
        cos2 = slope_weights(torch.from_numpy(pairs.clean_n[i][None, None]), res, 2)[0, 0]
        cos2_np = cos2.numpy().astype(np.float64)
        band = depth_edge_band(pairs.clean_n[i], pairs.loss_mask[i], 0.02)
        mask = same_surface_mask(pairs, i)
        bulk = same_surface_mask(pairs, i, BULK_SURFACE_N)
        acc["all"] += _sq_n(err, mask)
        acc["band"] += _sq_n(err, band & mask)
        acc["normal"] += _normal_sq_w(err, cos2_np, mask)
        acc["bulk"] += _sq_n(err, bulk)
        acc["bulk_normal"] += _normal_sq_w(err, cos2_np, bulk)
    return {
        "rmse_permille": _rms_permille(*acc["all"]),
        "edge_rmse_permille": _rms_permille(*acc["band"]),
        "normal_rmse_permille": _rms_permille(*acc["normal"]),
        "bulk_rmse_permille": _rms_permille(*acc["bulk"]),
        "bulk_normal_rmse_permille": _rms_permille(*acc["bulk_normal"]),
    }


def _sq_n(err: NDArray[np.float64], mask: NDArray[np.bool_]) -> tuple[float, float]:
    return float(np.sum(err[mask] ** 2)), float(np.count_nonzero(mask))


def _normal_sq_w(
    err: NDArray[np.float64], cos2: NDArray[np.float64], mask: NDArray[np.bool_]
) -> tuple[float, float]:
    seen = mask & (cos2 > MIN_COS**2)
    return float(np.sum(err[seen] ** 2 * cos2[seen] ** 2)), float(np.sum(cos2[seen]))


def _rms_permille(sq: float, weight: float) -> float:
    return 1e3 * float(np.sqrt(sq / max(weight, 1e-12)))


def _batched(
    fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    pairs: DepthPairs,
    idx: NDArray[np.int64],
    device: torch.device,
    batch: int = 6,
) -> NDArray[np.float32]:
    outs = []
    with torch.no_grad():
        for s in range(0, len(idx), batch):
            sel = idx[s : s + batch]
            d = torch.from_numpy(pairs.degraded_n[sel][:, None]).to(device)
            v = torch.from_numpy(pairs.degraded_valid[sel][:, None]).to(device)
            e = torch.from_numpy(pairs.edges[sel][:, None]).to(device)
            noisy = torch.from_numpy(pairs.noisy_n[sel][:, None]).to(device)
            outs.append(fn(d, v, side_inputs(e, noisy, d, v))[:, 0].cpu().numpy())
    return np.concatenate(outs)


def noisy_input(pairs: DepthPairs, idx: NDArray[np.int64]) -> NDArray[np.float32]:
    """(n, H, W) the noisy renders, the base standing in where they have no surface but the
    base has (their silhouettes differ): those pixels say nothing of the noisy depth."""
    return np.where(pairs.noisy_n[idx] < 1.0, pairs.noisy_n[idx], pairs.degraded_n[idx])


def _inputs(pairs: DepthPairs, idx: NDArray[np.int64]) -> dict:
    """Scores of the networks' two inputs: the noisy render and the pre-smoothed base."""
    return {
        "noisy": depth_scores(noisy_input(pairs, idx), pairs, idx),
        "presmoothed": depth_scores(pairs.degraded_n[idx], pairs, idx),
    }


def validate_regressor(model, pairs: DepthPairs, count: int, device: torch.device) -> dict:
    """Input and regressed depth scores."""
    idx = _subset(pairs, count)
    model.eval()
    return {
        "views": len(idx),
        **_inputs(pairs, idx),
        "regressor": depth_scores(_batched(model, pairs, idx, device), pairs, idx),
    }


def validate_ldm(
    nets: tuple | None,
    vae: DepthVAE,
    pairs: DepthPairs,
    count: int,
    device: torch.device,
    refines: ResidualUNet | None = None,
) -> dict:
    """VAE figures (clean latent decoded: its ceiling; degraded latent decoded), and with
    `nets` = (unet, controlnet) the sampled LDM at 1, 4 and 10 steps. With a `refines`
    regressor the degraded depth is its estimate (`guide_depth`), scored as `regressor`."""
    from pipeline.enhance.pipelines.depth_ldm import LDMModels, enhance_depth_ldm, guide_depth

    idx = _subset(pairs, count)
    vae.eval()
    out: dict = {"views": len(idx), **_inputs(pairs, idx)}
    if refines is not None:
        out["regressor"] = depth_scores(_batched(refines, pairs, idx, device), pairs, idx)

    def decode_of(name: str):
        def fn(d: torch.Tensor, v: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
            # The latent of the clean or the degraded depth, decoded with the degraded guide.
            sel = _current.pop(0)
            g = guide_depth(refines, d, v, e)
            clean = torch.from_numpy(pairs.clean_n[sel][:, None]).to(device)
            x = g if name == "degraded" else clean
            xp, vp, (h, w) = padded(x, v)
            gp, _, _ = padded(g, v)
            ep, _, _ = padded(e, v)
            return vae.decode(vae.encode(xp, vp).mean, gp, vp, ep)[..., :h, :w]

        return fn

    for name in ("clean", "degraded"):
        _current = [idx[s : s + 6] for s in range(0, len(idx), 6)]
        pred = _batched(decode_of(name), pairs, idx, device)
        out[f"vae_{name}_latent"] = depth_scores(pred, pairs, idx)
    if nets is not None:
        models = LDMModels(vae, nets[0].eval(), nets[1].eval(), refines)
        runs = [(1, 0.5), (4, 0.5), (10, 0.5), (4, 0.3), (4, 0.7)]
        for steps, strength in runs:

            def sample(
                d: torch.Tensor, v: torch.Tensor, e: torch.Tensor, n: int = steps,
                s: float = strength,
            ) -> torch.Tensor:
                return enhance_depth_ldm(models, d, v, n, s, 0, e)

            pred = _batched(sample, pairs, idx, device)
            out[f"ldm_{steps}_steps_strength_{strength}"] = depth_scores(pred, pairs, idx)
    return out
