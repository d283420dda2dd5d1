"""Geometric warp hint of the novel-view model: the reference image forward-warped into each target camera.

Every reference pixel with depth ``z > 0`` (metric camera z) is lifted to the world point
``X = R^T (z K_r^-1 [u, v, 1]^T - t)`` and projected into target camera ``w2c_t, K_t`` at continuous pixel
coordinates ``(u', v')`` and depth ``z'``. Splatting is z-buffered: ``nearest`` writes the point into the
pixel containing ``(u', v')``; ``bilinear`` spreads it over the 2x2 pixels around it with bilinear weights.
A target pixel keeps the contributions within ``depth_tolerance`` (relative) of its nearest depth and takes
their weight-normalised colour; pixels nothing reaches are invalid (colour 0).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import pixel_grid, project_points, unproject_pixels

FOOTPRINTS = ("nearest", "bilinear")
MIN_WEIGHT = 1e-6
"""Footprint weights at or below this (round-off of points on pixel centres) do not take part in the z-test."""


def _check(name: str, tensor: Tensor, shape: tuple[int | None, ...]) -> None:
    if tensor.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, tensor.shape)):
        dims = ",".join("*" if s is None else str(s) for s in shape)
        raise ValueError(f"{name} must have shape [{dims}], got {tuple(tensor.shape)}")


def _footprint(uv: Tensor, mode: str) -> tuple[Tensor, Tensor, Tensor]:
    """Integer pixel ``(col, row)`` ``[V,K,N]`` and weights ``[V,K,N]`` of points at ``uv [V,N,2]``."""
    if mode == "nearest":
        cell = uv.floor()
        return cell[..., 0][:, None], cell[..., 1][:, None], torch.ones_like(uv[..., 0])[:, None]
    base = (uv - 0.5).floor()
    frac = uv - 0.5 - base
    cols, rows, weights = [], [], []
    for dy in (0, 1):
        for dx in (0, 1):
            cols.append(base[..., 0] + dx)
            rows.append(base[..., 1] + dy)
            wx = frac[..., 0] if dx else 1 - frac[..., 0]
            wy = frac[..., 1] if dy else 1 - frac[..., 1]
            weights.append(wx * wy)
    return torch.stack(cols, 1), torch.stack(rows, 1), torch.stack(weights, 1)


def _bin_sums(index: Tensor, values: Tensor, bins: int) -> Tensor:
    """``out[r, p] = sum_{j : index[j] = p} values[r, j]`` (float64 ``values [R,M]``, ``index [M]`` in
    ``[0, bins)``), the same bits on every run: :func:`_sorted_bin_sums` on CUDA, where ``index_add`` adds
    with atomics or, under deterministic algorithms, in a serial per-bin loop (~13 ms per call on an H200);
    ``index_add`` elsewhere, deterministic on a CPU and ~10x faster there than the sort."""
    if index.device.type != "cuda":
        sums = torch.zeros(values.shape[0], bins, dtype=values.dtype, device=values.device)
        return sums.index_add(1, index, values)
    return _sorted_bin_sums(index, values, bins)


def _sorted_bin_sums(index: Tensor, values: Tensor, bins: int) -> Tensor:
    """:func:`_bin_sums` in 64-bit fixed point of ``2^-s`` units (``s`` per row, the largest that keeps the
    row's sum of magnitudes under ``2^61``; rounding ``<= 2^-(s+1)`` per value), as differences of prefix sums
    over a stable sort of ``index``: exact integer sums, the same bits on every run and device, no atomics. A bin
    that receives a NaN or an infinity is NaN (``index_add`` gives NaN or that infinity); the other bins keep
    their sums."""
    sorted_index, order = torch.sort(index, stable=True)
    values = values[:, order]
    finite = values.isfinite()
    values = torch.where(finite, values, 0.0)
    magnitude = values.abs().sum(-1, keepdim=True).clamp_min(torch.finfo(values.dtype).tiny)
    shift = (61 - torch.log2(magnitude).ceil()).clamp(-900, 900)
    fixed = torch.stack([torch.round(values * torch.exp2(shift)).to(torch.int64), (~finite).to(torch.int64)])
    prefix = F.pad(fixed.cumsum(-1), (1, 0))
    edges = torch.searchsorted(sorted_index, torch.arange(bins + 1, device=index.device, dtype=index.dtype))
    sums, non_finite = prefix[..., edges[1:]] - prefix[..., edges[:-1]]
    return torch.where(non_finite > 0, torch.nan, sums.to(values.dtype) * torch.exp2(-shift))


def forward_warp(
    reference: Tensor,
    depth: Tensor,
    reference_w2c: Tensor,
    reference_K: Tensor,
    target_w2c: Tensor,
    target_K: Tensor,
    size: int,
    footprint: str = "bilinear",
    depth_tolerance: float = 0.03,
) -> tuple[Tensor, Tensor]:
    """Forward-warp ``reference [C,H,W]`` into ``V`` target cameras; see the module docstring.

    Args:
        reference: image ``[C,H,W]`` (e.g. premultiplied RGBA in [0, 1]).
        depth: camera z of the reference ``[1,H,W]`` in world units, 0 = background.
        reference_w2c: OpenCV world-to-camera ``[4,4]``; reference_K: pixel intrinsics ``[3,3]`` of ``H x W``.
        target_w2c: ``[V,4,4]``; target_K: ``[V,3,3]`` pixel intrinsics of the ``size x size`` output.
        size: output side in pixels.
        footprint: ``nearest`` or ``bilinear`` (2x2).
        depth_tolerance: relative depth band ``z' <= z_min (1 + tol)`` of a pixel's surviving contributions.

    Returns:
        warped ``[V,C,size,size]`` (0 where invalid) and validity ``[V,1,size,size]`` in {0, 1}.
    """
    _check("reference", reference, (None, None, None))
    c, h, w = reference.shape
    _check("depth", depth, (1, h, w))
    _check("reference_w2c", reference_w2c, (4, 4))
    _check("reference_K", reference_K, (3, 3))
    _check("target_w2c", target_w2c, (None, 4, 4))
    v = target_w2c.shape[0]
    _check("target_K", target_K, (v, 3, 3))
    if footprint not in FOOTPRINTS:
        raise ValueError(f"footprint must be one of {FOOTPRINTS}, got {footprint!r}")
    if size < 1:
        raise ValueError(f"size must be positive, got {size}")
    if depth_tolerance < 0:
        raise ValueError(f"depth_tolerance must be >= 0, got {depth_tolerance}")
    dtype = torch.float64
    z = depth.reshape(-1).to(dtype)
    uv = pixel_grid(h, w, device=reference.device).reshape(-1, 2).to(dtype)
    source = z > 0  # background pixels (z = 0, or not a number) are masked, not dropped: no data-dependent
    colors = torch.where(source, reference.reshape(c, -1).to(dtype), 0.0)  # shape, so no host sync on CUDA
    points = unproject_pixels(uv, z, reference_w2c.to(dtype), reference_K.to(dtype))
    uv_t, z_t = project_points(points[None], target_w2c.to(dtype), target_K.to(dtype))  # [V,N,2], [V,N]
    cols, rows, weights = _footprint(uv_t, footprint)  # [V,K,N]
    depth_t = z_t[:, None].expand_as(weights)
    inside = (
        (cols >= 0) & (cols < size) & (rows >= 0) & (rows < size) & (depth_t > 0) & (weights > MIN_WEIGHT)
        & source
    )
    view = torch.arange(v, device=reference.device)[:, None, None].expand_as(weights)
    index = torch.where(inside, (view * size + rows) * size + cols, 0).long().reshape(-1)
    depth_t = torch.where(inside, depth_t, torch.inf).reshape(-1)
    weights = torch.where(inside, weights, 0.0).reshape(-1)
    nearest = torch.full((v * size * size,), torch.inf, dtype=dtype, device=reference.device)
    nearest = nearest.scatter_reduce(0, index, depth_t, "amin")
    keep = weights * (depth_t <= nearest[index] * (1 + depth_tolerance))
    k = weights.numel() // colors.shape[1]
    spread = colors[:, None].expand(c, k, colors.shape[1]).reshape(c, -1) * keep
    sums = _bin_sums(index, torch.cat([keep[None], spread]), v * size * size)
    total, accum = sums[0], sums[1:]
    valid = total > 0
    warped = torch.where(valid, accum / total.clamp_min(1e-12), 0.0)
    warped = warped.reshape(c, v, size, size).transpose(0, 1)
    return warped.to(reference.dtype), valid.reshape(v, 1, size, size).to(reference.dtype)


def resize_depth(depth: Tensor, size: int) -> Tensor:
    """Camera-z map ``[...,1,H,W]`` (0 = background) at ``size x size`` without mixing across the silhouette.

    Integer down-scaling takes the minimum foreground depth of each block (min-pooling; a block is
    foreground when any of its pixels is); other ratios use nearest-neighbour sampling.
    """
    if depth.ndim < 3 or depth.shape[-3] != 1:
        raise ValueError(f"depth must have shape [...,1,H,W], got {tuple(depth.shape)}")
    h, w = depth.shape[-2:]
    if (h, w) == (size, size):
        return depth
    flat = depth.reshape(-1, 1, h, w)
    if h == w and h % size == 0:
        far = torch.where(flat > 0, flat, torch.inf)
        pooled = -F.max_pool2d(-far, h // size)
        out = torch.where(torch.isinf(pooled), 0.0, pooled)
    else:
        out = F.interpolate(flat, size=(size, size), mode="nearest")
    return out.reshape(*depth.shape[:-2], size, size)
