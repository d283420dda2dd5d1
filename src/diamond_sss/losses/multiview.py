"""Multi-view geometric consistency (supplement Sec. D; the paper's Eq. 3.5 and 3.6; method.md Sec. 5).

For a source view ``i``, a target view ``j`` and foreground pixels ``x`` of ``i``::

    X = unproject(x, D_i(x))            (world point, camera-space depth D_i)
    (x', z_ij) = project(X, w2c_j, K_j)  (pixel coordinates and depth of X in view j)

* silhouette term: ``max(0, tau - S_j(x')) / tau`` with ``S_j`` the soft target silhouette, sampled
  bilinearly, and ``tau`` the tolerance ``sil_tolerance`` (default 1: ``1 - S_j(x')``). A point that lands
  where ``S_j >= tau`` costs nothing. With ``tau = 1`` the soft band of a mask's edge keeps pulling the source
  depth of boundary pixels towards the object's interior (measured, issue 58: cleaner boundaries and +1 dB on
  the demo's 9 images, expected depth 4 cm deeper; ``tau = 0.5`` keeps the depth and loses the dB). The
  gradient reaches ``D_i`` only where ``S_j`` varies (about one target pixel at a binary mask's edge): a point
  landing where ``S_j`` is flat 0 counts but is not moved, and opacity is reached only through ``D_i``;
* depth term: ``rho(shrink(n(z_ij) - n(D_j(x'))))`` with ``n(z) = (z - near) / (far - near)`` (Sec. D.3),
  ``shrink(d) = sign(d) max(|d| - delta, 0)`` for the tolerance ``delta = depth_tolerance`` and
  ``rho(d) = |d|`` or the Charbonnier ``sqrt(d^2 + eps^2) - eps``. The rendered depth is the alpha-normalised
  expected depth, in which each Gaussian counts at its centre's depth: on a surface tilted away from a camera
  the nearer centres win, so two views of the same correct surface disagree by about the splat size times the
  tilt (about 0.013 in normalised units for 0.05-wide splats on a plane seen 0 and 35 degrees off its normal).
  Residuals within ``delta`` are that precision, not an inconsistency, and cost nothing (default 0: every
  residual counts; 0.02 measured neutral on the demo's 9 images).

Filters (Sec. D.2): correspondences are dropped from both terms when the source depth is invalid
(non-finite, ``<= 0``, or source alpha below ``alpha_threshold``), when ``z_ij <= near``, or when
``x'`` falls outside image ``j``. The depth term additionally drops ``x'`` with
``S_j(x') < sil_threshold``, with an invalid target depth anywhere in the bilinear footprint (or
target alpha below ``alpha_threshold``), and occluded points, ``n(z_ij) - n(D_j(x')) > occlusion_tol``.
A target depth that is invalid where ``X`` lands is exactly what the silhouette term penalises, so
it does not filter that term. Pairs whose target has no silhouette of its own (``tgt_silhouette_valid``
False, e.g. a lattice view with no image, whose ``S_j`` is then only used to filter the depth term) give no
silhouette correspondences. Each term is the sum of its per-correspondence losses divided by its
own count of valid correspondences, and is exactly 0 (with a graph) when that count is 0.

Gradients reach the source depth ``D_i`` through both terms (via ``X``) and the target depth ``D_j``
through the depth term (bilinear sampling); the target silhouette ``S_j`` is a constant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import project_points, sample_bilinear, unproject_pixels
from diamond_sss.utils import rng

TargetMode = Literal["nearest-k", "random"]

# Bilinear footprint test: the sampled validity indicator must be at least this (all taps valid).
_FOOTPRINT_VALID = 0.999


@dataclass(frozen=True)
class MultiViewConfig:
    """Settings of the multi-view silhouette and depth losses.

    Attributes:
        pairs_per_step: (source, target) view pairs sampled per optimisation step.
        pixels_per_pair: foreground pixels sampled in the source view of each pair.
        target_mode: ``"nearest-k"`` (target among the ``nearest_k`` closest camera centres) or ``"random"``.
        nearest_k: neighbourhood size of ``"nearest-k"``.
        sil_threshold: depth-term silhouette tolerance: ``x'`` with ``S_j(x') <`` this is ignored.
        occlusion_tol: occlusion tolerance in normalised depth units (fraction of ``far - near``).
        charbonnier_eps: ``None`` for the L1 depth residual, else the Charbonnier ``eps`` (normalised units).
        alpha_threshold: rendered alpha below which a pixel's depth counts as invalid.
        sil_tolerance: silhouette value ``tau`` at and above which a landing point costs nothing (``1``: ``1 - S``).
        depth_tolerance: normalised depth residual ``delta`` that costs nothing (``0``: every residual counts).
    """

    pairs_per_step: int = 4
    pixels_per_pair: int = 1024
    target_mode: TargetMode = "nearest-k"
    nearest_k: int = 4
    sil_threshold: float = 0.5
    occlusion_tol: float = 0.02
    charbonnier_eps: float | None = None
    alpha_threshold: float = 0.5
    sil_tolerance: float = 1.0
    depth_tolerance: float = 0.0

    def __post_init__(self) -> None:
        if self.pairs_per_step < 1 or self.pixels_per_pair < 1 or self.nearest_k < 1:
            raise ValueError("pairs_per_step, pixels_per_pair and nearest_k must be positive")
        if self.target_mode not in ("nearest-k", "random"):
            raise ValueError(f"target_mode must be 'nearest-k' or 'random', got {self.target_mode!r}")
        if not 0.0 <= self.sil_threshold <= 1.0 or not 0.0 <= self.alpha_threshold <= 1.0:
            raise ValueError("sil_threshold and alpha_threshold must lie in [0, 1]")
        if not 0.0 < self.sil_tolerance <= 1.0:
            raise ValueError(f"sil_tolerance must lie in (0, 1], got {self.sil_tolerance}")
        if self.depth_tolerance < 0.0:
            raise ValueError(f"depth_tolerance must be non-negative, got {self.depth_tolerance}")
        if self.occlusion_tol < 0.0:
            raise ValueError(f"occlusion_tol must be non-negative, got {self.occlusion_tol}")
        if self.charbonnier_eps is not None and self.charbonnier_eps <= 0.0:
            raise ValueError(f"charbonnier_eps must be positive or None, got {self.charbonnier_eps}")


@dataclass
class MultiViewTerms:
    """Normalised multi-view losses (scalars) and their counts of valid correspondences (int64 scalars)."""

    silhouette: Tensor
    depth: Tensor
    n_silhouette: Tensor
    n_depth: Tensor


def sample_view_pairs(
    camera_centers: Tensor,
    num_pairs: int,
    mode: TargetMode,
    k: int,
    generator: torch.Generator | None = None,
    candidate_targets: Tensor | None = None,
    source_views: Tensor | None = None,
) -> Tensor:
    """Sample up to ``num_pairs`` (source, target) pairs. ``camera_centers [V,3]`` -> ``[P,2]`` int64.

    Each pair draws its source ``i`` uniformly from ``source_views [S]`` (e.g. the views of a batch; all ``V``
    views when None), then its target from ``candidate_targets`` (all views if None) minus ``source_views[i]``:
    uniformly (``"random"``) or uniformly among the ``k`` candidates whose centres are closest to the source's
    (``"nearest-k"``, distances in the dtype of ``camera_centers``). A row is ``(i, target view)``, so ``i`` is
    the source view when ``source_views`` is None. A source with no other candidate gives no pair (``P`` may be
    less than ``num_pairs``). Deterministic for a seeded ``generator``.
    """
    if camera_centers.ndim != 2 or camera_centers.shape[-1] != 3:
        raise ValueError(f"camera_centers must have shape [V,3], got {tuple(camera_centers.shape)}")
    if mode not in ("nearest-k", "random"):
        raise ValueError(f"mode must be 'nearest-k' or 'random', got {mode!r}")
    if k < 1 or num_pairs < 0:
        raise ValueError(f"need k >= 1 and num_pairs >= 0, got k={k}, num_pairs={num_pairs}")
    num_views = camera_centers.shape[0]
    centers = camera_centers.detach().cpu()
    if candidate_targets is None:
        candidates = torch.arange(num_views)
    else:
        candidates = torch.unique(candidate_targets.detach().cpu().to(torch.int64))
        if candidates.numel() and (candidates.min() < 0 or candidates.max() >= num_views):
            raise ValueError(f"candidate_targets must index the {num_views} views")
    views = torch.arange(num_views) if source_views is None else source_views.detach().cpu().to(torch.int64)
    if views.numel() == 0 or views.min() < 0 or views.max() >= num_views:
        raise ValueError(f"source_views must be a non-empty list of indices of the {num_views} views")
    pairs = []
    for _ in range(num_pairs):
        i = int(rng.randint(views.numel(), 1, generator=generator))
        source = views[i]
        pool = candidates[candidates != source]
        if pool.numel() == 0:
            continue
        if mode == "nearest-k":
            distance = (centers[pool] - centers[source]).norm(dim=-1)
            pool = pool[torch.argsort(distance, stable=True)[:k]]
        pairs.append((i, int(pool[rng.randint(pool.numel(), 1, generator=generator)])))
    return torch.tensor(pairs, dtype=torch.int64).reshape(-1, 2).to(camera_centers.device)


def sample_foreground_pixels(mask: Tensor, num: int, generator: torch.Generator | None = None) -> Tensor:
    """Sample up to ``num`` distinct pixels with ``mask > 0.5``; returns their centres ``uv [n,2]``.

    ``uv = (col + 0.5, row + 0.5)``, ``n = min(num, #foreground)``, in random order; deterministic
    for a seeded ``generator``. ``mask [H,W]``.
    """
    if mask.ndim != 2:
        raise ValueError(f"mask must have shape [H,W], got {tuple(mask.shape)}")
    if num < 0:
        raise ValueError(f"num must be non-negative, got {num}")
    rows, cols = torch.nonzero(mask.detach() > 0.5, as_tuple=True)
    order = rng.randperm(rows.numel(), generator=generator, device=rows.device)[:num]
    uv = torch.stack([cols[order], rows[order]], dim=-1).to(torch.float32) + 0.5
    return uv.to(mask.device)


def _valid_depth(depth: Tensor, alpha: Tensor, alpha_threshold: float) -> Tensor:
    return torch.isfinite(depth) & (depth > 0) & torch.isfinite(alpha) & (alpha >= alpha_threshold)


def _check_views(name: str, depth: Tensor, alpha: Tensor, w2c: Tensor, K: Tensor, batch: int) -> None:
    if depth.ndim != 3 or depth.shape[0] != batch:
        raise ValueError(f"{name}_depth must have shape [P,H,W] with P={batch}, got {tuple(depth.shape)}")
    if alpha.shape != depth.shape:
        raise ValueError(f"{name}_alpha {tuple(alpha.shape)} must match {name}_depth {tuple(depth.shape)}")
    if w2c.shape != (batch, 4, 4) or K.shape != (batch, 3, 3):
        raise ValueError(
            f"{name}_w2c / {name}_K must have shapes [P,4,4] / [P,3,3] with P={batch}, "
            f"got {tuple(w2c.shape)} / {tuple(K.shape)}"
        )


def multiview_losses_batched(
    src_depth: Tensor,
    src_alpha: Tensor,
    src_uv: Tensor,
    src_w2c: Tensor,
    src_K: Tensor,
    tgt_depth: Tensor,
    tgt_alpha: Tensor,
    tgt_silhouette: Tensor,
    tgt_w2c: Tensor,
    tgt_K: Tensor,
    near: float,
    far: float,
    cfg: MultiViewConfig,
    src_uv_valid: Tensor | None = None,
    tgt_silhouette_valid: Tensor | None = None,
) -> MultiViewTerms:
    """Multi-view silhouette and depth losses over ``P`` view pairs (see the module docstring).

    Shapes: ``src_depth, src_alpha [P,Hs,Ws]``; ``src_uv [P,n,2]`` source pixel centres (``+0.5``);
    ``src_w2c, tgt_w2c [P,4,4]``; ``src_K, tgt_K [P,3,3]``; ``tgt_depth, tgt_alpha, tgt_silhouette
    [P,Ht,Wt]``; ``src_uv_valid [P,n]`` bool marks real entries when pairs have fewer than ``n``
    pixels; ``tgt_silhouette_valid [P]`` bool marks the pairs whose ``tgt_silhouette`` is a real silhouette
    (None: all), the others give no silhouette correspondences. Depths are camera-space z in scene units; ``near < far`` are the scene clipping planes.
    Each term is normalised by its count of valid correspondences over all pairs.
    """
    if not far > near:
        raise ValueError(f"need far > near, got near={near}, far={far}")
    batch = src_depth.shape[0] if src_depth.ndim == 3 else -1
    _check_views("src", src_depth, src_alpha, src_w2c, src_K, batch)
    _check_views("tgt", tgt_depth, tgt_alpha, tgt_w2c, tgt_K, batch)
    if tgt_silhouette.shape != tgt_depth.shape:
        raise ValueError(
            f"tgt_silhouette {tuple(tgt_silhouette.shape)} must match tgt_depth {tuple(tgt_depth.shape)}"
        )
    if src_uv.ndim != 3 or src_uv.shape[0] != batch or src_uv.shape[-1] != 2:
        raise ValueError(f"src_uv must have shape [P,n,2] with P={batch}, got {tuple(src_uv.shape)}")
    if src_uv_valid is not None and src_uv_valid.shape != src_uv.shape[:2]:
        raise ValueError(
            f"src_uv_valid must have shape {tuple(src_uv.shape[:2])}, got {tuple(src_uv_valid.shape)}"
        )
    if tgt_silhouette_valid is not None and tgt_silhouette_valid.shape != (batch,):
        raise ValueError(f"tgt_silhouette_valid must have shape ({batch},), got {tuple(tgt_silhouette_valid.shape)}")
    dtype = src_depth.dtype
    src_height, src_width = src_depth.shape[-2:]
    tgt_height, tgt_width = tgt_depth.shape[-2:]
    span = far - near

    # Source lookup at the sampled pixel centres (exact texels, so gradients reach D_i(x) directly).
    uv = src_uv.to(dtype)
    entry_valid = torch.isfinite(uv).all(-1)
    if src_uv_valid is not None:
        entry_valid = entry_valid & src_uv_valid.to(torch.bool)
    uv = torch.where(entry_valid.unsqueeze(-1), uv, torch.full_like(uv, 0.5))
    cols = uv[..., 0].floor().long()
    rows = uv[..., 1].floor().long()
    inside_src = (cols >= 0) & (cols < src_width) & (rows >= 0) & (rows < src_height)
    flat_index = (rows.clamp(0, src_height - 1) * src_width + cols.clamp(0, src_width - 1)).reshape(batch, -1)
    d_src = torch.gather(src_depth.reshape(batch, -1), 1, flat_index)
    a_src = torch.gather(src_alpha.reshape(batch, -1).to(dtype), 1, flat_index)
    valid = entry_valid & inside_src & _valid_depth(d_src, a_src, cfg.alpha_threshold)
    d_src = torch.where(valid, d_src, torch.ones_like(d_src))

    # Back-project into the world, project into the target view.
    points = unproject_pixels(uv, d_src, src_w2c.to(dtype), src_K.to(dtype))
    uv_tgt, z_tgt = project_points(points, tgt_w2c.to(dtype), tgt_K.to(dtype))
    valid = valid & torch.isfinite(uv_tgt).all(-1) & torch.isfinite(z_tgt) & (z_tgt > near)
    in_image = (uv_tgt[..., 0] >= 0) & (uv_tgt[..., 0] < tgt_width)
    in_image = in_image & (uv_tgt[..., 1] >= 0) & (uv_tgt[..., 1] < tgt_height)
    valid = valid & in_image
    uv_tgt = torch.where(valid.unsqueeze(-1), uv_tgt, torch.full_like(uv_tgt, 0.5))
    z_tgt = torch.where(valid, z_tgt, torch.full_like(z_tgt, near + 0.5 * span))

    # Silhouette term: max(0, tau - S_j(x')) / tau, the silhouette is a constant.
    silhouette = sample_bilinear(tgt_silhouette.detach().to(dtype), uv_tgt)
    sil_valid = valid if tgt_silhouette_valid is None else valid & tgt_silhouette_valid.to(torch.bool)[:, None]
    tau = cfg.sil_tolerance
    sil_residual = torch.where(sil_valid, (tau - silhouette).clamp_min(0.0) / tau, torch.zeros_like(silhouette))
    n_silhouette = sil_valid.sum()
    loss_silhouette = sil_residual.sum() / n_silhouette.clamp_min(1).to(dtype)

    # Depth term on the target's rendered depth (differentiable, sanitised so no NaN enters the graph).
    tgt_valid_map = _valid_depth(tgt_depth.detach(), tgt_alpha.detach(), cfg.alpha_threshold)
    tgt_depth_clean = torch.where(tgt_valid_map, tgt_depth, torch.zeros_like(tgt_depth))
    footprint_valid = sample_bilinear(tgt_valid_map.to(dtype), uv_tgt) >= _FOOTPRINT_VALID
    d_tgt = sample_bilinear(tgt_depth_clean, uv_tgt)
    difference = (z_tgt - d_tgt) / span
    depth_valid = valid & footprint_valid & (silhouette >= cfg.sil_threshold)
    depth_valid = depth_valid & (difference.detach() <= cfg.occlusion_tol)
    difference = F.softshrink(torch.where(depth_valid, difference, torch.zeros_like(difference)), cfg.depth_tolerance)
    if cfg.charbonnier_eps is None:
        depth_residual = difference.abs()
    else:
        eps = cfg.charbonnier_eps
        depth_residual = torch.sqrt(difference.square() + eps * eps) - eps
    depth_residual = torch.where(depth_valid, depth_residual, torch.zeros_like(depth_residual))
    n_depth = depth_valid.sum()
    loss_depth = depth_residual.sum() / n_depth.clamp_min(1).to(dtype)
    return MultiViewTerms(
        silhouette=loss_silhouette, depth=loss_depth, n_silhouette=n_silhouette, n_depth=n_depth
    )


def multiview_losses(
    src_depth: Tensor,
    src_alpha: Tensor,
    src_uv: Tensor,
    src_w2c: Tensor,
    src_K: Tensor,
    tgt_depth: Tensor,
    tgt_alpha: Tensor,
    tgt_silhouette: Tensor,
    tgt_w2c: Tensor,
    tgt_K: Tensor,
    near: float,
    far: float,
    cfg: MultiViewConfig,
) -> MultiViewTerms:
    """Multi-view silhouette and depth losses of one (source, target) pair; see the module docstring.

    ``src_depth, src_alpha [Hs,Ws]``, ``src_uv [n,2]`` (pixel centres, e.g. from
    :func:`sample_foreground_pixels`), ``src_w2c [4,4]``, ``src_K [3,3]``, ``tgt_depth, tgt_alpha,
    tgt_silhouette [Ht,Wt]``, ``tgt_w2c [4,4]``, ``tgt_K [3,3]``. Depth is camera-space z.
    """
    for name, x, ndim in (("src_depth", src_depth, 2), ("src_uv", src_uv, 2), ("tgt_depth", tgt_depth, 2)):
        if x.ndim != ndim:
            raise ValueError(f"{name} must be {ndim}-D for a single pair, got shape {tuple(x.shape)}")
    return multiview_losses_batched(
        src_depth[None],
        src_alpha[None],
        src_uv[None],
        src_w2c[None],
        src_K[None],
        tgt_depth[None],
        tgt_alpha[None],
        tgt_silhouette[None],
        tgt_w2c[None],
        tgt_K[None],
        near,
        far,
        cfg,
    )
