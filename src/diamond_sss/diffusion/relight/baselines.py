"""Reference relighting baselines the diffusion model must beat (``benchmarks/relight_quality.py``).

Lambertian re-shading: with surface points ``x`` (unprojected depth), unit normals ``n`` and a point light
at ``p``, the shading is ``S(x) = max(0, n . (p - x) / |p - x|) / |p - x|^2``. A per-channel albedo is
fitted to the source image by least squares over the mask, ``a_c = sum I_c S_src / sum S_src^2``, and the
prediction is ``a_c S_tgt`` (linear radiance, 0 outside the mask).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import pixel_grid, unproject_pixels


def lambertian_shading(
    depth: Tensor, normals_world: Tensor, w2c: Tensor, K: Tensor, light_position: Tensor
) -> Tensor:
    """``S [H,W,1]`` of a point light at ``light_position [3]`` (see module doc); 0 where ``depth <= 0``."""
    height, width = depth.shape[:2]
    uv = pixel_grid(height, width).reshape(-1, 2)
    points = unproject_pixels(uv, depth.reshape(-1), w2c, K).reshape(height, width, 3)
    offset = light_position.to(points) - points
    distance_sq = offset.square().sum(-1, keepdim=True).clamp_min(1e-12)
    cosine = (F.normalize(normals_world, dim=-1) * F.normalize(offset, dim=-1)).sum(-1, keepdim=True)
    return cosine.clamp_min(0.0) / distance_sq * (depth > 0)


def lambertian_relight(
    source: Tensor,
    mask: Tensor,
    depth: Tensor,
    normals_world: Tensor,
    w2c: Tensor,
    K: Tensor,
    source_light: Tensor,
    target_lights: Tensor,
) -> Tensor:
    """Re-shade ``source [H,W,3]`` from ``source_light [3]`` to each of ``target_lights [L,3]`` -> ``[L,H,W,3]``."""
    keep = (mask > 0.5).to(source.dtype)
    shading_src = lambertian_shading(depth, normals_world, w2c, K, source_light) * keep
    albedo = (source * shading_src).sum((0, 1)) / shading_src.square().sum((0, 1)).clamp_min(1e-12)
    shading = torch.stack([lambertian_shading(depth, normals_world, w2c, K, p) for p in target_lights])
    return (albedo * shading * keep).clamp(0.0, 1.0)
