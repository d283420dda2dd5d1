"""Reference depth as a sparse reconstruction renders it, for fine-tuning the warp-hint model.

At inference the warp hint is splatted with the preliminary reconstruction's depth (a 3- or 5-view run), at
training with the capture's true depth. What differs there (``benchmarks/sparse_depth.py``, measured at the real
views of 3- and 5-view reconstructions): a smooth relative error (2-3% spread, 6-12% on a 3-view torus) and an
outline moved by a pixel. :func:`perturb_depth` draws both per map, turning a true camera-z map ``z``
(0 = background) into a plausible rendered one:

- the outline moved: the support ``z > 0`` dilated (``e > 0``) or eroded (``e < 0``) by ``|e| <= edge_px``
  pixels, each new support pixel taking the mean depth of the old support in the ``(2e+1)^2`` box around it;
- a smooth relative error: ``z' = z (1 + sigma f)``, ``f`` standard normal on a ``(grid+1)^2`` lattice over
  the map, bilinearly interpolated, ``sigma`` uniform in ``[0, relative]``.

Pixel radii are in the map's pixels times ``pixel_scale`` (the warp source is ``warp_supersample`` times the
image). Everything is drawn from ``generator``, in a fixed order per map, so a batch is a pure function of it.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.utils import rng


def dilate(support: Tensor, radius: int) -> Tensor:
    """``[B,1,H,W]`` 0/1 mask dilated by a ``(2r+1)^2`` square (Chebyshev distance ``<= radius``)."""
    if radius <= 0:
        return support
    return F.max_pool2d(support, 2 * radius + 1, stride=1, padding=radius)


def erode(support: Tensor, radius: int) -> Tensor:
    """``[B,1,H,W]`` 0/1 mask eroded by a ``(2r+1)^2`` square; outside the map counts as support."""
    if radius <= 0:
        return support
    return -F.max_pool2d(-support, 2 * radius + 1, stride=1, padding=radius)


def box_mean_depth(depth: Tensor, support: Tensor, radius: int) -> Tensor:
    """Mean of ``depth`` over the ``support`` pixels in the ``(2r+1)^2`` box around each pixel (0 where the box
    holds none)."""
    k = 2 * radius + 1
    total = F.avg_pool2d(depth * support, k, stride=1, padding=radius)
    count = F.avg_pool2d(support, k, stride=1, padding=radius)
    return torch.where(count > 0, total / count.clamp_min(1e-12), 0.0)


def move_outline(depth: Tensor, pixels: int) -> Tensor:
    """``depth [B,1,H,W]`` with its support dilated (``pixels > 0``; new pixels take the box mean of the old depth
    around them) or eroded (``pixels < 0``) by ``|pixels|``."""
    old = (depth > 0).to(depth.dtype)
    if pixels < 0:
        return depth * erode(old, -pixels)
    filled = box_mean_depth(depth, old, pixels)
    return torch.where(dilate(old, pixels) > 0, torch.where(old > 0, depth, filled), 0.0)


def smooth_relative_error(depth: Tensor, sigma: float | Tensor, generator: torch.Generator, grid: int = 4) -> Tensor:
    """Factors ``(1 + sigma f).clamp(min=0.05)`` ``[B,1,H,W]`` for ``depth [B,1,H,W]``: ``f`` standard normal on a
    ``(grid+1)^2`` lattice per map, bilinearly interpolated over it; ``sigma`` a number or ``[B]``."""
    batch, _, height, width = depth.shape
    lattice = rng.randn(batch, 1, grid + 1, grid + 1, generator=generator, device=depth.device, dtype=depth.dtype)
    field = F.interpolate(lattice, size=(height, width), mode="bilinear", align_corners=True)
    sigma = torch.as_tensor(sigma, dtype=depth.dtype).to(depth.device).reshape(-1, 1, 1, 1)
    return (1 + sigma * field).clamp_min(0.05)


def perturb_depth(
    depth: Tensor,
    generator: torch.Generator,
    share: float,
    relative: float,
    edge_px: int,
    grid: int = 4,
    pixel_scale: int = 1,
) -> Tensor:
    """``depth [B,1,H,W]`` (camera z, 0 = background) with a ``share`` of its maps perturbed (module docstring).

    ``share = 0`` returns ``depth`` itself and draws nothing from ``generator``.
    """
    if depth.ndim != 4 or depth.shape[1] != 1:
        raise ValueError(f"depth must have shape [B,1,H,W], got {tuple(depth.shape)}")
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"share must be in [0, 1], got {share}")
    if not (math.isfinite(relative) and relative >= 0 and edge_px >= 0):
        raise ValueError(f"relative and edge_px must be finite and >= 0, got {relative} and {edge_px}")
    if share == 0.0:
        return depth
    batch = depth.shape[0]
    chosen = rng.rand(batch, generator=generator) < share
    edges = rng.randint(2 * edge_px + 1, batch, generator=generator) - edge_px
    sigmas = relative * rng.rand(batch, generator=generator)
    factors = smooth_relative_error(depth, sigmas, generator, grid)
    out = []
    for b in range(batch):
        if not bool(chosen[b]):
            out.append(depth[b : b + 1])
            continue
        z = move_outline(depth[b : b + 1], int(edges[b]) * pixel_scale)
        out.append(z * factors[b : b + 1] * (z > 0))
    return torch.cat(out)
