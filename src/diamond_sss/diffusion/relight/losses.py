"""Fine-tuning losses of the relighting model, on model-space images ``[B,3,H,W]`` in [-1, 1].

``L = |v - v*|^2 + w_l1 L1(x0, x) + w_ssim (1 - SSIM(x0, x)) + w_lpips LPIPS(x0, x)
      + w_cycle L1(x0_back, x_src) + w_low L1(pool_k(x0), pool_k(x))``

``x0`` is the clean image implied by the velocity prediction; ``x0_back`` relights ``x0`` back to the source
light; ``pool_k`` is a ``k x k`` average pool (the blur-aware low-frequency term: it weights the smooth light
transport that blurry predictions get right, independently of high-frequency detail).
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from diamond_sss.diffusion.relight.config import RelightLossWeights
from diamond_sss.losses.photometric import ssim_per_image


def to_unit(x: Tensor) -> Tensor:
    """Model space [-1, 1] -> [0, 1], channels last ``[B,H,W,3]`` (for SSIM / LPIPS)."""
    return ((x + 1.0) * 0.5).clamp(0.0, 1.0).permute(0, 2, 3, 1)


def low_frequency_l1(pred: Tensor, target: Tensor, kernel: int) -> Tensor:
    """``mean |pool_k(pred) - pool_k(target)|`` with a ``k x k`` average pool."""
    if kernel < 1:
        raise ValueError(f"low-frequency kernel must be >= 1, got {kernel}")
    return (F.avg_pool2d(pred, kernel) - F.avg_pool2d(target, kernel)).abs().mean()


def image_losses(
    pred_clean: Tensor, target: Tensor, weights: RelightLossWeights, lpips: nn.Module | None = None
) -> dict[str, Tensor]:
    """Weighted L1, DSSIM, LPIPS and low-frequency terms of ``pred_clean`` against ``target`` (unweighted keys)."""
    unit_pred, unit_target = to_unit(pred_clean), to_unit(target)
    terms = {
        "l1": (pred_clean - target).abs().mean(),
        "ssim": 1.0 - ssim_per_image(unit_pred, unit_target).mean(),
        "low_frequency": low_frequency_l1(pred_clean, target, weights.low_frequency_kernel),
    }
    if lpips is not None:
        terms["lpips"] = lpips(unit_pred, unit_target).mean()
    return terms
