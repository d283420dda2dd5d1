"""Conditioning image of the relighting model: source image, depth, camera-space normals, mask (8 channels).

All channels are mapped to about [-1, 1] at the model's resolution:
source ``2 srgb(I) - 1``; depth as normalised nearness ``2 (1/z - min) / (max - min) - 1`` over the mask
(:func:`~diamond_sss.diffusion.geometry.base.depth_to_nearness`; Depth Anything's relative disparity is normalised
the same way); normals ``R n`` in the OpenCV camera frame; mask ``2 m - 1``. Background depth and normals are 0 / -1 as written below.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import linear_to_srgb, srgb_to_linear
from diamond_sss.diffusion.geometry.base import MASK_THRESHOLD


def image_to_model(linear_rgb: Tensor) -> Tensor:
    """Linear radiance ``[B,H,W,3]`` -> model space ``2 srgb - 1`` ``[B,3,H,W]``."""
    return linear_to_srgb(linear_rgb.clamp(0.0, 1.0)).permute(0, 3, 1, 2) * 2.0 - 1.0


def model_to_image(x: Tensor) -> Tensor:
    """Model space ``[B,3,H,W]`` -> linear radiance ``[B,H,W,3]`` in [0, 1]."""
    return srgb_to_linear(((x.permute(0, 2, 3, 1) + 1.0) * 0.5).clamp(0.0, 1.0))


def conditioning_image(
    source_linear: Tensor, nearness: Tensor, normals_cam: Tensor, mask: Tensor, resolution: int
) -> Tensor:
    """Stack ``[B,H,W,3|1|3|1]`` maps into the ``[B,8,R,R]`` conditioning image (area-resized to ``R``)."""
    parts = {
        "source": (source_linear, 3),
        "nearness": (nearness, 1),
        "normals": (normals_cam, 3),
        "mask": (mask, 1),
    }
    batch_hw = source_linear.shape[:3]
    for name, (tensor, channels) in parts.items():
        if tensor.ndim != 4 or tensor.shape[-1] != channels:
            raise ValueError(f"{name} must have shape [B,H,W,{channels}], got {tuple(tensor.shape)}")
        if tensor.shape[:3] != batch_hw:
            raise ValueError(f"{name} has shape {tuple(tensor.shape)}, expected [B,H,W] = {tuple(batch_hw)}")
        if not bool(torch.isfinite(tensor).all()):
            raise ValueError(f"{name} map has non-finite values (NaN or inf): check the image or geometry source")
    keep = (mask > MASK_THRESHOLD).to(source_linear.dtype)
    stacked = torch.cat(
        [
            linear_to_srgb(source_linear.clamp(0.0, 1.0)) * 2.0 - 1.0,
            nearness * 2.0 - 1.0,
            normals_cam * keep,
            mask * 2.0 - 1.0,
        ],
        dim=-1,
    ).permute(0, 3, 1, 2)
    if stacked.shape[-2:] != (resolution, resolution):
        stacked = F.interpolate(stacked, size=(resolution, resolution), mode="area")
    return stacked.contiguous()
