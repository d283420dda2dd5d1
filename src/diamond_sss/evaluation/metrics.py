"""Image metrics on sRGB images in [0,1], full frame, black background (how results are reported).

PSNR ``= 10 log10(1 / MSE)``; SSIM (Gaussian window 11, sigma 1.5); LPIPS (VGG, optional: ``None`` when
its weights are unavailable); masked PSNR (MSE over the ground-truth mask's pixels only); mask IoU of the
rendered alpha and the ground-truth mask, both thresholded at 0.5.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.losses.lpips import LPIPS
from diamond_sss.losses.photometric import ssim_per_image


@dataclass
class ImageMetrics:
    """Metrics of one image."""

    psnr: float
    ssim: float
    lpips: float | None
    masked_psnr: float
    mask_iou: float

    def to_dict(self) -> dict:
        return asdict(self)


def psnr(pred: Tensor, target: Tensor, mask: Tensor | None = None) -> float:
    """PSNR in dB of images in [0,1] (``[H,W,C]``); over ``mask > 0.5`` pixels when a mask is given."""
    err = (pred - target) ** 2
    if mask is not None:
        keep = (mask[..., 0] > 0.5)
        if not bool(keep.any()):
            return float("nan")
        err = err[keep]
    mse = float(err.mean())
    return 100.0 if mse <= 1e-10 else 10.0 * math.log10(1.0 / mse)


def mask_iou(alpha: Tensor, mask: Tensor, threshold: float = 0.5) -> float:
    """Intersection over union of ``alpha > t`` and ``mask > t``; 1 when both are empty."""
    a = alpha > threshold
    b = mask > threshold
    union = int((a | b).sum())
    return 1.0 if union == 0 else int((a & b).sum()) / union


def image_metrics(pred_linear: Tensor, target_linear: Tensor, pred_alpha: Tensor, target_mask: Tensor,
                  lpips_model: LPIPS | None = None) -> ImageMetrics:
    """All metrics of one image pair given in linear radiance ``[H,W,3]`` (converted to sRGB here)."""
    pred = linear_to_srgb(pred_linear.detach().float().cpu())
    target = linear_to_srgb(target_linear.detach().float().cpu())
    ssim_value = float(ssim_per_image(pred[None], target[None])[0])
    lpips_value = None
    if lpips_model is not None:
        with torch.no_grad():
            device = next(lpips_model.parameters()).device
            lpips_value = float(lpips_model(pred[None].to(device), target[None].to(device)).reshape(-1)[0])
    return ImageMetrics(
        psnr=psnr(pred, target),
        ssim=ssim_value,
        lpips=lpips_value,
        masked_psnr=psnr(pred, target, target_mask.detach().cpu()),
        mask_iou=mask_iou(pred_alpha.detach().cpu(), target_mask.detach().cpu()),
    )


def mean_metrics(rows: list[ImageMetrics]) -> dict:
    """Means over images (``lpips`` stays ``None`` when unavailable; NaN masked PSNRs are skipped)."""
    if not rows:
        raise ValueError("no images to average")
    out = {}
    for key in ("psnr", "ssim", "masked_psnr", "mask_iou"):
        values = [getattr(r, key) for r in rows if not math.isnan(getattr(r, key))]
        out[key] = sum(values) / len(values) if values else float("nan")
    lpips_values = [r.lpips for r in rows if r.lpips is not None]
    out["lpips"] = sum(lpips_values) / len(lpips_values) if lpips_values else None
    out["images"] = len(rows)
    return out
