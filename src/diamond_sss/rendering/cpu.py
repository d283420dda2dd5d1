"""Tiled pure-PyTorch Gaussian rasterizer (any device; autograd, with an analytic backward for compositing).

Same math as gsplat's CUDA rasterizer: for a pixel centre ``p`` and the depth-sorted Gaussians ``i`` whose
bounding boxes overlap the pixel's tile,

    q_i = d^T Sigma_2d,i^-1 d,  d = p - mu_i
    alpha_i = min(0.999, o_i exp(-q_i / 2)),  alpha_i := 0 if alpha_i < 1/255
    T_i = prod_{j<i} (1 - alpha_j),  C(p) = sum_i alpha_i T_i c_i

and compositing stops before the first Gaussian that would bring the transmittance to 1e-4 or below.

Every image is cut into ``tile_size x tile_size`` tiles; each tile keeps the list of Gaussians whose box
overlaps it. Tiles are sorted by list length and processed in batches, each padded to its longest list,
so the work is a handful of batched tensor operations instead of loops over Gaussians or pixels.
The exponent ``ln o - q/2`` of all (pixel, Gaussian) pairs of a batch is one matrix product of a per-pixel
quadratic basis with per-Gaussian coefficients, in tile-local coordinates to keep float32 cancellation small.
The bounding boxes hold every contribution above 1/255, so the result does not depend on the tile size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from diamond_sss.rendering.projection import ALPHA_THRESHOLD, tile_grid_shape

MAX_ALPHA = 0.999
"""Per-Gaussian alpha is clamped to this (gsplat)."""

MIN_TRANSMITTANCE = 1e-4
"""Compositing stops before a Gaussian that would bring the transmittance to this or below (gsplat)."""

PAD_LOG_ALPHA = -1e30
"""Log-alpha of padding slots: their alpha is exp(-1e30) = 0."""


@dataclass
class TileLists:
    """Depth-sorted Gaussian lists of the non-empty tiles of ``n_images`` images.

    Attributes:
        tile_ids: ``[T]`` global tile index ``image * tiles_x * tiles_y + ty * tiles_x + tx``, longest list first.
        entries: ``[T,K]`` indices into the visible entries, front to back, padded with ``-1``.
        counts: ``[T]`` list lengths (non-increasing).
        tiles_per_entry: ``[E]`` number of tiles each entry overlaps.
    """

    tile_ids: Tensor
    entries: Tensor
    counts: Tensor
    tiles_per_entry: Tensor


def intersect_tiles(
    means2d: Tensor,
    radii: Tensor,
    depths: Tensor,
    image_ids: Tensor,
    width: int,
    height: int,
    tile_size: int,
) -> TileLists:
    """Assign ``E`` visible entries (``means2d [E,2]``, int ``radii [E,2]``, ``depths [E]``, ``image_ids [E]``)
    to the tiles their boxes ``mu +- r`` overlap, as gsplat's ``isect_tiles``; lists sorted by depth.

    Tile range of an entry along x: ``[floor((u - r_x) / s), ceil((u + r_x) / s))`` clipped to the grid.
    """
    tiles_x, tiles_y = tile_grid_shape(width, height, tile_size)
    device = means2d.device
    with torch.no_grad():
        order = torch.sort(depths, stable=True).indices
        centre = means2d[order].float() / tile_size
        half = radii[order].float() / tile_size
        lo = torch.floor(centre - half).clamp(min=0).long()
        hi = torch.ceil(centre + half).long()
        hi = torch.minimum(hi, torch.tensor([tiles_x, tiles_y], device=device))
        lo = torch.minimum(lo, hi)
        span = hi - lo
        counts = span[:, 0] * span[:, 1]
        tiles_per_entry = torch.zeros_like(counts).scatter_(0, order, counts)

        n_pairs = int(counts.sum())
        pair_entry = torch.repeat_interleave(torch.arange(len(order), device=device), counts)
        first_pair = torch.cumsum(counts, 0) - counts
        local = torch.arange(n_pairs, device=device) - first_pair[pair_entry]
        width_in_tiles = span[pair_entry, 0].clamp_min(1)
        tx = lo[pair_entry, 0] + local % width_in_tiles
        ty = lo[pair_entry, 1] + local // width_in_tiles
        pair_tile = image_ids[order][pair_entry].long() * (tiles_x * tiles_y) + ty * tiles_x + tx

        pair_tile, by_tile = torch.sort(pair_tile, stable=True)
        pair_entry = order[pair_entry[by_tile]]
        tile_ids, tile_counts = torch.unique_consecutive(pair_tile, return_counts=True)
        rank = torch.arange(n_pairs, device=device) - torch.repeat_interleave(
            torch.cumsum(tile_counts, 0) - tile_counts, tile_counts
        )
        tile_row = torch.repeat_interleave(torch.arange(len(tile_ids), device=device), tile_counts)

        by_length = torch.sort(tile_counts, descending=True, stable=True).indices
        row_of_tile = torch.empty_like(by_length)
        row_of_tile[by_length] = torch.arange(len(by_length), device=device)
        max_count = int(tile_counts.max()) if len(tile_counts) else 0
        entries = torch.full((len(tile_ids), max_count), -1, dtype=torch.long, device=device)
        entries[row_of_tile[tile_row], rank] = pair_entry
    return TileLists(
        tile_ids=tile_ids[by_length],
        entries=entries,
        counts=tile_counts[by_length],
        tiles_per_entry=tiles_per_entry,
    )


def tile_pixel_offsets(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Pixel centres of a tile relative to its centre, ``[P,2]`` with ``P = tile_size^2`` in row-major order."""
    coords = torch.arange(tile_size, dtype=dtype, device=device) + 0.5 - 0.5 * tile_size
    v, u = torch.meshgrid(coords, coords, indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)


def quadratic_basis(offsets: Tensor) -> Tensor:
    """Per-pixel basis ``[-u^2/2, -u v, -v^2/2, u, v, 1]`` of tile-local offsets ``[P,2] -> [P,6]``."""
    u, v = offsets.unbind(-1)
    return torch.stack([-0.5 * u * u, -u * v, -0.5 * v * v, u, v, torch.ones_like(u)], dim=-1)


def log_alpha_coefficients(mean: Tensor, conic: Tensor, log_opacity: Tensor) -> Tensor:
    """Coefficients ``[...,6]`` with ``basis(p) . coef = ln o - q/2`` at tile-local pixel offsets ``p``.

    With ``d = p - m`` and conic ``(a, b, c)``: ``q = a d_u^2 + 2 b d_u d_v + c d_v^2``, expanded in powers of
    ``p`` so that one matrix product gives the log-alpha of every (pixel, Gaussian) pair of a tile.
    """
    mu, mv = mean.unbind(-1)
    a, b, c = conic.unbind(-1)
    lin_u = a * mu + b * mv
    lin_v = b * mu + c * mv
    const = log_opacity - 0.5 * (mu * lin_u + mv * lin_v)
    return torch.stack([a, b, c, lin_u, lin_v, const], dim=-1)


def composite_tiles(log_alpha: Tensor, features: Tensor) -> tuple[Tensor, Tensor]:
    """Front-to-back compositing of ``log_alpha [T,P,K]`` (``ln o - q/2`` per pixel and depth-sorted slot)
    and slot features ``[T,K,C]``. Returns premultiplied ``features [T,P,C]`` and ``alpha [T,P]``.

    ``alpha_i = min(0.999, exp(log_alpha_i))``, zeroed below 1/255; ``w_i = alpha_i T_i`` with
    ``T_i = prod_{j<i} (1 - alpha_j)``, zeroed from the first slot whose inclusive transmittance is at most 1e-4.
    Differentiable (hand-written backward, see :class:`_Composite`).
    """
    return _Composite.apply(log_alpha, features)


class _Composite(torch.autograd.Function):
    """Compositing with an analytic backward pass (about half the memory traffic of plain autograd).

    With ``g_w = dL/dw`` and ``w_k = alpha_k T_k``:
    ``dL/dalpha_j = g_w,j T_j - (sum_{k>j} g_w,k w_k) / (1 - alpha_j)`` and
    ``dL/dlog_alpha = alpha dL/dalpha`` where the alpha is neither clamped nor cut off.
    """

    @staticmethod
    def forward(ctx, log_alpha: Tensor, features: Tensor) -> tuple[Tensor, Tensor]:
        # Clamped before exp: exp of large negative numbers (denormal results) is very slow on CPUs.
        alpha = log_alpha.clamp(min=math.log(ALPHA_THRESHOLD) - 1.0, max=math.log(MAX_ALPHA)).exp_()
        torch.threshold_(alpha, ALPHA_THRESHOLD, 0.0)
        log_transmit = torch.log1p(alpha.neg())
        log_t_incl = torch.cumsum(log_transmit, dim=-1)
        transmit = log_t_incl.sub(log_transmit)
        log_t_min = math.log(MIN_TRANSMITTANCE)
        if log_t_incl.numel() and bool(log_t_incl[..., -1].min() <= log_t_min):
            transmit.clamp_min_(log_t_min - 1.0).exp_().masked_fill_(log_t_incl <= log_t_min, 0.0)
        else:
            transmit.exp_()
        weights = alpha * transmit
        ctx.save_for_backward(log_alpha, alpha, transmit, weights, features)
        # (f^T w^T)^T rather than w f: BLAS is several times faster with the long axis K inside.
        return _transposed_matmul(features.transpose(-1, -2), weights.transpose(-1, -2)), weights.sum(-1)

    @staticmethod
    def backward(ctx, grad_features: Tensor, grad_alpha: Tensor) -> tuple[Tensor, Tensor]:
        log_alpha, alpha, transmit, weights, features = ctx.saved_tensors
        grad_weights = torch.baddbmm(grad_alpha[..., None], grad_features, features.transpose(-1, -2))
        grad_slot_features = _transposed_matmul(grad_features.transpose(-1, -2), weights)
        behind = grad_weights * weights
        behind = behind.sum(-1, keepdim=True) - behind.cumsum(-1)
        grad_log_alpha = grad_weights.mul_(transmit).sub_(behind.div_(1.0 - alpha)).mul_(alpha)
        grad_log_alpha.masked_fill_(log_alpha >= math.log(MAX_ALPHA), 0.0)
        return grad_log_alpha, grad_slot_features


def _transposed_matmul(a: Tensor, b: Tensor) -> Tensor:
    """``(a @ b)^T`` over the last two axes."""
    return (a @ b).transpose(-1, -2)


def _absgrad_hook(
    absgrad: Tensor, rows: Tensor, slots: Tensor, offsets: Tensor, means: Tensor, conics: Tensor
):
    """Hook on the log_alpha ``[T,P,K]`` of one tile batch. Adds the AbsGS gradient of the 2D means,
    ``sum_p |dL/dl_p dl_p/dmu|`` (``l``: log-alpha; absolute values per pixel before the sum, as gsplat),
    to the rows ``rows[entry]`` of ``absgrad [R,2]``.
    ``slots [T,K]`` are entry indices (``-1`` = padding), ``means [T,K,2]`` tile-local, ``conics [T,K,3]``.
    """

    def hook(grad: Tensor) -> None:
        with torch.no_grad():
            d = offsets[None, :, None, :] - means[:, None, :, :]
            a, b, c = conics[:, None, :, 0], conics[:, None, :, 1], conics[:, None, :, 2]
            du = (grad * (a * d[..., 0] + b * d[..., 1])).abs().sum(1)
            dv = (grad * (b * d[..., 0] + c * d[..., 1])).abs().sum(1)
            per_slot = torch.stack([du, dv], dim=-1) * (slots >= 0)[..., None]
            absgrad.index_add_(0, rows[slots.clamp_min(0)].reshape(-1), per_slot.reshape(-1, 2).to(absgrad))

    return hook


def rasterize_entries(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    radii: Tensor,
    depths: Tensor,
    image_ids: Tensor,
    n_images: int,
    width: int,
    height: int,
    tile_size: int = 16,
    max_batch_elements: int = 1 << 18,
    absgrad: Tensor | None = None,
    absgrad_rows: Tensor | None = None,
) -> tuple[Tensor, Tensor, TileLists]:
    """Rasterize ``E`` visible screen-space Gaussians into ``n_images`` images.

    ``means2d [E,2]`` pixels, ``conics [E,3]``, ``opacities [E]``, ``features [E,C]``, int ``radii [E,2]``,
    ``depths [E]`` (sort keys), ``image_ids [E]``. Tiles are batched so that a batch's ``[T,P,K]`` tensors hold
    at most ``max_batch_elements`` values. When ``absgrad [R,2]`` is given, the AbsGS gradient of entry ``e``'s
    2D mean is added to its row ``absgrad_rows[e]`` (default ``e``) during the backward pass.

    Returns ``features [n_images,H,W,C]``, ``alpha [n_images,H,W,1]`` (both premultiplied, black background)
    and the tile lists.
    """
    tiles_x, tiles_y = tile_grid_shape(width, height, tile_size)
    n_pixels = tile_size * tile_size
    n_channels = features.shape[-1]
    dtype, device = means2d.dtype, means2d.device
    lists = intersect_tiles(means2d, radii, depths, image_ids, width, height, tile_size)

    offsets = tile_pixel_offsets(tile_size, dtype, device)
    basis = quadratic_basis(offsets)
    pad_coef = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, PAD_LOG_ALPHA], dtype=dtype, device=device)
    log_opacities = torch.log(opacities)
    local_tile = lists.tile_ids % (tiles_x * tiles_y)
    tile_centres = torch.stack([local_tile % tiles_x, local_tile // tiles_x], dim=-1).to(dtype)
    tile_centres = (tile_centres + 0.5) * tile_size

    if absgrad is not None and absgrad_rows is None:
        absgrad_rows = torch.arange(len(means2d), device=device)

    outputs = []
    start = 0
    while start < len(lists.tile_ids):
        length = max(int(lists.counts[start]), 1)
        stop = min(len(lists.tile_ids), start + max(1, max_batch_elements // (length * n_pixels)))
        slots = lists.entries[start:stop, :length]
        is_pad = slots < 0
        safe = slots.clamp_min(0)
        local_means = means2d[safe] - tile_centres[start:stop, None, :]
        slot_conics = conics[safe]
        coef = log_alpha_coefficients(local_means, slot_conics, log_opacities[safe])
        coef = torch.where(is_pad[..., None], pad_coef, coef)
        log_alpha = basis @ coef.transpose(-1, -2)
        if absgrad is not None and log_alpha.requires_grad:
            log_alpha.register_hook(
                _absgrad_hook(
                    absgrad, absgrad_rows, slots, offsets, local_means.detach(), slot_conics.detach()
                )
            )
        slot_features = torch.where(is_pad[..., None], 0.0, features[safe])
        colors, alpha = composite_tiles(log_alpha, slot_features)
        outputs.append(torch.cat([colors, alpha[..., None]], dim=-1))
        start = stop

    n_tiles = n_images * tiles_x * tiles_y
    flat = torch.zeros(n_tiles, n_pixels, n_channels + 1, dtype=dtype, device=device)
    if outputs:
        flat = flat.index_copy(0, lists.tile_ids, torch.cat(outputs, dim=0))
    else:  # nothing visible: keep the images attached to the graph so that every input gets a zero gradient
        flat = flat + 0.0 * (means2d.sum() + conics.sum() + opacities.sum() + features.sum())
    image = flat.reshape(n_images, tiles_y, tiles_x, tile_size, tile_size, n_channels + 1)
    image = image.permute(0, 1, 3, 2, 4, 5).reshape(n_images, tiles_y * tile_size, tiles_x * tile_size, -1)
    image = image[:, :height, :width]
    return image[..., :n_channels], image[..., n_channels:], lists
