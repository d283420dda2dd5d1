"""Shading hint: a directional Lambertian re-shading of the source image, computed from the model's inputs.

Like DiLightNet's radiance hints, the hint gives the network the target light's coarse shading so it only has
to learn what Lambertian shading misses (subsurface glow, shadows, highlights). Everything comes from the
conditioning image and the light codes, so every caller gets the same hint:

- light direction ``l`` (unit, source camera frame) from the degree-1 SH terms of the code
  ``(Y_1, Y_2, Y_3) = C1 (-y, z, -x)``; distance ``d`` (object radii) from its last entry;
- shading ``s = max(0, n . l) / d^2`` with the conditioning's camera-space normals ``n``, diffused over the
  surface in screen space like screen-space subsurface scattering: ``s <- (G_sigma * (s m)) / (G_sigma * m)``
  inside the mask ``m`` (``G_sigma`` a Gaussian of ``sigma`` pixels; ``sigma = 0`` keeps plain Lambertian
  shading). On the held-out relighting objects sigma = 2 px at 64 px scores 22.19 dB against 21.74 without;
- per-channel albedo fitted to the linear source image over the mask, ``a_c = sum I_c s_src / sum s_src^2``;
- hint ``a_c s_tgt`` (linear radiance in [0, 1], 0 outside the mask), returned in model space ``2 srgb - 1``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import linear_to_srgb, srgb_to_linear
from diamond_sss.diffusion.relight.conditioning import MASK_THRESHOLD
from diamond_sss.shading.sh import SH_C1


def direction_from_code(code: Tensor) -> tuple[Tensor, Tensor]:
    """Unit light direction ``[...,3]`` (camera frame) and distance ``[...,1]`` (radii) of a light code."""
    x, y, z = -code[..., 3] / SH_C1, -code[..., 1] / SH_C1, code[..., 2] / SH_C1
    return F.normalize(torch.stack([x, y, z], dim=-1), dim=-1), code[..., 9:10]


def gaussian_blur(image: Tensor, sigma: float) -> Tensor:
    """Separable Gaussian blur of ``[B,C,H,W]`` with standard deviation ``sigma`` pixels (3-sigma support,
    replicated borders); ``sigma = 0`` returns the input."""
    if sigma <= 0.0:
        return image
    radius = max(1, math.ceil(3.0 * sigma))
    offsets = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    kernel = kernel / kernel.sum()
    channels = image.shape[1]
    horizontal = kernel.view(1, 1, 1, -1).expand(channels, 1, 1, -1)
    vertical = kernel.view(1, 1, -1, 1).expand(channels, 1, -1, 1)
    image = F.conv2d(F.pad(image, (radius, radius, 0, 0), mode="replicate"), horizontal, groups=channels)
    return F.conv2d(F.pad(image, (0, 0, radius, radius), mode="replicate"), vertical, groups=channels)


def lambertian_hint(
    conditioning: Tensor, target_code: Tensor, source_code: Tensor, blur_sigma: float = 0.0
) -> Tensor:
    """Hint ``[B,3,R,R]`` (model space) for ``conditioning [B,8,R,R]``, light codes ``[B,10]`` and a screen-space
    diffusion of ``blur_sigma`` pixels."""
    source = srgb_to_linear(((conditioning[:, 0:3] + 1.0) * 0.5).clamp(0.0, 1.0))
    normals = F.normalize(conditioning[:, 4:7], dim=1, eps=1e-8)
    keep = ((conditioning[:, 7:8] + 1.0) * 0.5 > MASK_THRESHOLD).to(source.dtype)

    def shading(code: Tensor) -> Tensor:
        direction, distance = direction_from_code(code)
        cosine = torch.einsum("bchw,bc->bhw", normals, direction).unsqueeze(1).clamp_min(0.0) * keep
        diffused = gaussian_blur(cosine, blur_sigma) / gaussian_blur(keep, blur_sigma).clamp_min(1e-3) * keep
        return diffused / distance.square().clamp_min(1e-8)[..., None, None]

    shading_source = shading(source_code)
    albedo = (source * shading_source).sum((2, 3), keepdim=True) / shading_source.square().sum(
        (2, 3), keepdim=True
    ).clamp_min(1e-8)
    relit = (albedo * shading(target_code)).clamp(0.0, 1.0)
    return linear_to_srgb(relit) * 2.0 - 1.0
