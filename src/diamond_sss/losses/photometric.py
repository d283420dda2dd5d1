"""Photometric reconstruction terms (supplement Eq. A.1, first line).

Images are ``[B,H,W,C]`` channels-last float tensors (linear radiance during training).
"""

from __future__ import annotations

import functools

import torch
from pytorch_msssim import ssim as _msssim_ssim
from torch import Tensor

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


def _check_pair(pred: Tensor, target: Tensor) -> None:
    if pred.ndim != 4:
        raise ValueError(f"expected images of shape [B,H,W,C], got pred of shape {tuple(pred.shape)}")
    if pred.shape != target.shape:
        raise ValueError(
            f"pred {tuple(pred.shape)} and target {tuple(target.shape)} must have the same shape"
        )


def _check_weights(weights: Tensor, batch: int) -> None:
    if weights.shape != (batch,):
        raise ValueError(f"weights must have shape [B] = [{batch}], got {tuple(weights.shape)}")


def l1_per_image(pred: Tensor, target: Tensor) -> Tensor:
    """Mean absolute error of each image, ``L1_b = mean_{x,c} |pred - target|``. ``[B,H,W,C] -> [B]``."""
    _check_pair(pred, target)
    return (pred - target).abs().mean(dim=(1, 2, 3))


RMSE_EPS = 1e-8
"""Added under the root of :func:`rmse_per_image` so that its gradient stays finite where an image matches exactly."""


def rmse_per_image(pred: Tensor, target: Tensor) -> Tensor:
    """Root mean squared error of each image, ``RMSE_b = sqrt(mean_{x,c} (pred - target)^2 + eps)``, the quantity
    that PSNR measures (``PSNR_b = -20 log10 RMSE_b`` for a data range of 1). ``[B,H,W,C] -> [B]``."""
    _check_pair(pred, target)
    return ((pred - target).square().mean(dim=(1, 2, 3)) + RMSE_EPS).sqrt()


PIXEL_ERRORS = {"l1": l1_per_image, "rmse": rmse_per_image}
"""The per-image error beside D-SSIM in :func:`photometric_loss`, by the name ``losses.photometric_error`` gives."""


@functools.lru_cache(maxsize=16)
def ssim_window(channels: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    """pytorch_msssim's separable Gaussian window ``g_i = exp(-(i - 5)^2 / (2 sigma^2)) / sum``, ``[C,1,1,11]``, made
    once per device and dtype (the library makes it on the host at every call: on CUDA a copy that waits for the
    GPU at every training step)."""
    with torch.inference_mode(False):  # made inside an evaluation, it is still usable by a training step
        coords = torch.arange(SSIM_WINDOW, dtype=torch.float32, device=device) - SSIM_WINDOW // 2
        window = torch.exp(-(coords**2) / (2 * SSIM_SIGMA**2))
        window = window / window.sum()
        return window.to(dtype).reshape(1, 1, 1, SSIM_WINDOW).repeat(channels, 1, 1, 1)


def ssim_per_image(pred: Tensor, target: Tensor) -> Tensor:
    """Gaussian-window SSIM (window 11, sigma 1.5: :func:`ssim_window`, ``data_range = 1``) of each image,
    channel-averaged.

    Wraps ``pytorch_msssim.ssim`` (NCHW inside). ``[B,H,W,C] -> [B]``. Both sides must be at least
    11 pixels (the window size).
    """
    _check_pair(pred, target)
    if min(pred.shape[1], pred.shape[2]) < SSIM_WINDOW:
        raise ValueError(
            f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, "
            f"got {pred.shape[1]}x{pred.shape[2]}"
        )
    nchw_pred = pred.permute(0, 3, 1, 2)
    nchw_target = target.permute(0, 3, 1, 2)
    window = ssim_window(pred.shape[-1], pred.device, pred.dtype)
    return _msssim_ssim(nchw_pred, nchw_target, data_range=1.0, size_average=False, win=window)


def dssim_per_image(pred: Tensor, target: Tensor) -> Tensor:
    """Structural dissimilarity ``1 - SSIM`` of each image. ``[B,H,W,C] -> [B]``."""
    return 1.0 - ssim_per_image(pred, target)


def weighted_mean(values: Tensor, weights: Tensor | None) -> Tensor:
    """``(1/B) sum_b w_b v_b`` (plain mean when ``weights`` is None). ``[B] -> []``.

    The weights are absolute, not normalised within the batch: an image of weight ``alpha`` contributes
    ``alpha`` times what a real image (weight 1) does whatever else the batch holds, so that at batch size 1
    and in a batch of generated images alone the down-weighting still acts (supplement Sec. C.2/C.3: the
    generated images' photometric losses are down-weighted by alpha). Weights must be non-negative: they are
    checked where they are made (the training config, the pipeline), not here, so that a training step never
    reads a value back from the device.
    """
    if weights is None:
        return values.mean()
    _check_weights(weights, values.shape[0])
    return (weights.to(values) * values).mean()


def l1_loss(pred: Tensor, target: Tensor, weights: Tensor | None = None) -> Tensor:
    """Per-image-weighted L1, ``(1/B) sum_b w_b L1_b``. ``[B,H,W,C] -> []``."""
    return weighted_mean(l1_per_image(pred, target), weights)


def dssim_loss(pred: Tensor, target: Tensor, weights: Tensor | None = None) -> Tensor:
    """Per-image-weighted ``1 - SSIM``, ``(1/B) sum_b w_b (1 - SSIM_b)``. ``[B,H,W,C] -> []``."""
    return weighted_mean(dssim_per_image(pred, target), weights)


def photometric_loss(
    pred: Tensor, target: Tensor, lambda_dssim: float, weights: Tensor | None = None, error: str = "l1"
) -> Tensor:
    """Mixed photometric objective of Eq. A.1.

    ``L = (1/B) sum_b w_b [(1 - l) E_b + l (1 - SSIM_b)]`` with ``l = lambda_dssim`` in ``[0, 1]`` and ``E_b`` the
    image's ``error`` (:data:`PIXEL_ERRORS`): ``L1_b`` (Eq. A.1) or ``RMSE_b``.
    ``weights [B]`` are per-image weights (e.g. ``alpha = 0.5`` for diffusion-generated images, 1 for
    real ones); ``None`` weighs every image 1. ``[B,H,W,C] -> []``.
    """
    if not 0.0 <= lambda_dssim <= 1.0:
        raise ValueError(f"lambda_dssim must lie in [0, 1], got {lambda_dssim}")
    if error not in PIXEL_ERRORS:
        raise ValueError(f"photometric error must be one of {sorted(PIXEL_ERRORS)}, got {error!r}")
    per_image = (1.0 - lambda_dssim) * PIXEL_ERRORS[error](pred, target)
    if lambda_dssim > 0.0:
        per_image = per_image + lambda_dssim * dssim_per_image(pred, target)
    return weighted_mean(per_image, weights)
