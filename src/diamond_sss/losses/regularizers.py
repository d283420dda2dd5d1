"""Regularisers of the SSS-3DGS objective (supplement Eq. A.2 - A.7, Tab. 3).

Image-space tensors are channels last: attribute and image maps ``[B,H,W,C]``, opacity and masks
``[B,H,W,1]`` with values in ``[0, 1]``, depth ``[B,H,W,1]`` (camera-space z). Every masked mean
divides by the mask's sum and is exactly 0 for an empty mask.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import camera_centers, pixel_grid, unproject_pixels

DEFAULT_EPS = 1e-6
ENHANCE_SHARPNESS = 10.0


def _check_map(name: str, x: Tensor, channels: int | None = None) -> None:
    if x.ndim != 4 or (channels is not None and x.shape[-1] != channels):
        expect = f"[B,H,W,{channels}]" if channels is not None else "[B,H,W,C]"
        raise ValueError(f"{name} must have shape {expect}, got {tuple(x.shape)}")


def _check_same_pixels(name: str, x: Tensor, ref_name: str, ref: Tensor) -> None:
    if x.shape[:3] != ref.shape[:3]:
        raise ValueError(
            f"{name} {tuple(x.shape)} and {ref_name} {tuple(ref.shape)} must share batch and pixel dimensions"
        )


def masked_mean(values: Tensor, mask: Tensor | None) -> Tensor:
    """``sum(M v) / sum(M)`` over all elements, ``M`` broadcast to ``values``; plain mean if ``mask`` is None.

    Returns exactly 0 (with a graph) when the mask or ``values`` is empty.
    """
    if mask is None:
        return values.mean() if values.numel() else values.sum()
    mask = mask.to(values).expand_as(values)
    return safe_ratio((mask * values).sum(), mask.sum())


def safe_ratio(numerator: Tensor, denominator: Tensor) -> Tensor:
    """``numerator / denominator`` for a non-negative denominator; ``0 / 0 = 0`` (keeps the graph)."""
    return numerator / denominator.clamp_min(torch.finfo(numerator.dtype).tiny)


def mask_bce_loss(alpha: Tensor, mask: Tensor, eps: float = DEFAULT_EPS) -> Tensor:
    """Eq. A.4: ``mean_x -[M log a + (1 - M) log(1 - a)]`` with ``a = clamp(alpha, eps, 1 - eps)``.

    ``alpha`` is the accumulated opacity, ``mask`` the image mask, both ``[B,H,W,1]``; mean over all pixels.
    """
    _check_map("alpha", alpha, 1)
    _check_map("mask", mask, 1)
    _check_same_pixels("alpha", alpha, "mask", mask)
    a = alpha.clamp(eps, 1.0 - eps)
    mask = mask.to(a)
    return -(mask * torch.log(a) + (1.0 - mask) * torch.log1p(-a)).mean()


def mask_entropy_loss(alpha: Tensor, eps: float = DEFAULT_EPS) -> Tensor:
    """Binary entropy of the accumulated opacity, ``mean_x -[a log a + (1 - a) log(1 - a)]``, in nats.

    Minimal (0) when every pixel is fully opaque or fully transparent: pushes opacity to 0/1
    (``lambda_mask_entropy``, Tab. 3). ``a = clamp(alpha, eps, 1 - eps)``, ``alpha [B,H,W,1]``.
    """
    _check_map("alpha", alpha, 1)
    a = alpha.clamp(eps, 1.0 - eps)
    return -(a * torch.log(a) + (1.0 - a) * torch.log1p(-a)).mean()


@dataclass(frozen=True)
class EdgeWeights:
    """What Eq. A.5 takes from the image and the mask, per direction (x, then y): the pair mask ``M_d`` ``[B,H',W']``,
    the edge weight ``e_d = exp(-mean_c |d_d I|)`` and ``sum M_d``. One step's smoothed attributes share them
    (:func:`edge_weights`), so that the image's differences are taken once, not once per attribute."""

    directions: tuple[tuple[Tensor, Tensor, Tensor], ...]
    image_shape: torch.Size


def edge_weights(image: Tensor, mask: Tensor | None = None, like: Tensor | None = None) -> EdgeWeights:
    """:class:`EdgeWeights` of ``image [B,H,W,C']`` and ``mask [B,H,W,1]`` (all ones if None), in the dtype and on
    the device of ``like`` (default ``image``)."""
    _check_map("image", image)
    like = image if like is None else like
    if mask is None:
        mask = torch.ones_like(image[..., :1], dtype=like.dtype)
    _check_map("mask", mask, 1)
    _check_same_pixels("mask", mask, "image", image)
    mask = mask.to(like)
    image = image.to(like)
    directions = []
    for dim in (2, 1):
        length = image.shape[dim] - 1
        grad_image = (image.narrow(dim, 1, length) - image.narrow(dim, 0, length)).abs().mean(-1)
        pair_mask = (mask.narrow(dim, 1, length) * mask.narrow(dim, 0, length)).squeeze(-1)
        directions.append((pair_mask, torch.exp(-grad_image), pair_mask.sum()))
    return EdgeWeights(tuple(directions), image.shape)


def bilateral_smoothness_loss(attribute: Tensor, image: Tensor, mask: Tensor | None = None,
                              edges: EdgeWeights | None = None) -> Tensor:
    """Eq. A.5, edge-aware smoothness of an attribute map (base colour, roughness, metallic, s).

    With forward differences ``d_x f(i,j) = f(i,j+1) - f(i,j)`` (and ``d_y`` along rows),
    ``g_d = mean_c |d_d attr|`` and ``e_d = exp(-mean_c |d_d I|)``::

        L = sum_{d in x,y} sum M_d g_d e_d / sum M_d,

    where ``M_d`` is the product of the mask at both pixels of a difference (all ones if ``mask`` is
    None). Summing the two directions gives the L1 norm of the gradient. ``attribute [B,H,W,C]``,
    ``image [B,H,W,C']``, ``mask [B,H,W,1]`` -> scalar. ``edges``: :func:`edge_weights` of ``image`` and ``mask``,
    made once for several attributes (the same values as without).
    """
    _check_map("attribute", attribute)
    _check_same_pixels("attribute", attribute, "image", image)
    if edges is None:
        edges = edge_weights(image, mask, like=attribute)
    elif edges.image_shape != image.shape:
        raise ValueError(f"edges were made for an image of shape {tuple(edges.image_shape)}, got {tuple(image.shape)}")
    total = attribute.new_zeros(())
    for dim, (pair_mask, edge, pairs) in zip((2, 1), edges.directions, strict=True):
        length = attribute.shape[dim] - 1
        grad_attr = (attribute.narrow(dim, 1, length) - attribute.narrow(dim, 0, length)).abs().mean(-1)
        weighted = pair_mask * grad_attr * edge
        total = total + safe_ratio(weighted.sum(), pairs)
    return total


def enhancement_weight(image: Tensor, sharpness: float = ENHANCE_SHARPNESS) -> Tensor:
    """Blending weight of Eq. A.6, per pixel: ``sw = sigmoid(k (mean_c I - 0.5))``, ``k = sharpness``.

    The R3DGS release does not contain this term, so the choice is ours: a per-pixel sigmoid of the
    channel-mean brightness centred at 0.5. Bright pixels (highlights, ``sw -> 1``) get the darkened
    target ``I^2``, dark pixels (shadows, ``sw -> 0``) the brightened ``1 - (1 - I)^2``.
    ``[B,H,W,C] -> [B,H,W,1]``.
    """
    return torch.sigmoid(sharpness * (image.mean(dim=-1, keepdim=True) - 0.5))


def enhancement_target(image: Tensor, sharpness: float = ENHANCE_SHARPNESS) -> Tensor:
    """Pseudo-target of Eq. A.6: ``T = sw I^2 + (1 - sw)(1 - (1 - I)^2)``, ``I`` clamped to ``[0, 1]``.

    ``sw`` from :func:`enhancement_weight`. ``[B,H,W,C] -> [B,H,W,C]``.
    """
    _check_map("image", image)
    image = image.clamp(0.0, 1.0)
    sw = enhancement_weight(image, sharpness)
    return sw * image.square() + (1.0 - sw) * (1.0 - (1.0 - image).square())


def enhancement_loss(
    base_color: Tensor, image: Tensor, mask: Tensor | None = None, sharpness: float = ENHANCE_SHARPNESS
) -> Tensor:
    """Eq. A.6 (R3DGS enhancement loss as used by SSS-3DGS): ``mean over M of |T - b|``, channel-mean L1.

    ``T = enhancement_target(I)`` carries no gradient. ``base_color [B,H,W,3]``, ``image [B,H,W,3]``,
    ``mask [B,H,W,1]`` -> scalar.
    """
    _check_map("base_color", base_color)
    _check_same_pixels("base_color", base_color, "image", image)
    target = enhancement_target(image.detach(), sharpness).to(base_color)
    return masked_mean((target - base_color).abs().mean(-1, keepdim=True), mask)


def base_color_prior_loss(base_color: Tensor, image: Tensor, mask: Tensor | None = None) -> Tensor:
    """Base-colour prior (``lambda_base_color``, Tab. 3): ``mean over M of mean_c |b - I|``.

    Neither the supplement nor method.md defines this term; we use the simplest prior with the
    same unit as the image: the rendered base colour ``b`` is pulled towards the observed linear
    radiance ``I`` (no gradient), a weak albedo initialisation cue next to :func:`enhancement_loss`.
    ``base_color [B,H,W,3]``, ``image [B,H,W,3]``, ``mask [B,H,W,1]`` -> scalar.
    """
    _check_map("base_color", base_color)
    _check_map("image", image, base_color.shape[-1])
    _check_same_pixels("base_color", base_color, "image", image)
    return masked_mean((base_color - image.detach().to(base_color)).abs().mean(-1, keepdim=True), mask)


def _batched_camera(name: str, x: Tensor, batch: int, shape: tuple[int, int]) -> Tensor:
    if x.shape == shape:
        return x.expand(batch, *shape)
    if x.shape == (batch, *shape):
        return x
    raise ValueError(
        f"{name} must have shape {list(shape)} or [B,{shape[0]},{shape[1]}], got {tuple(x.shape)}"
    )


def normals_from_depth(depth: Tensor, w2c: Tensor, K: Tensor) -> Tensor:
    """World-space pseudo-normals of a depth map under local planarity (Eq. A.2's ``N~``).

    Every pixel centre is back-projected to ``P = unproject(uv, D)``; with central differences
    ``dP_u = P(i,j+1) - P(i,j-1)`` and ``dP_v = P(i+1,j) - P(i-1,j)`` (one-sided at the border),
    ``N~ = normalize(dP_u x dP_v)``, flipped to face the camera (``N~ . (C - P) >= 0``).
    Degenerate pixels give the zero vector. Depth discontinuities are not treated specially.
    ``depth [B,H,W,1]``, ``w2c [B,4,4] or [4,4]``, ``K [B,3,3] or [3,3]`` -> ``[B,H,W,3]``.
    """
    _check_map("depth", depth, 1)
    batch, height, width, _ = depth.shape
    w2c = _batched_camera("w2c", w2c, batch, (4, 4)).to(depth)
    K = _batched_camera("K", K, batch, (3, 3)).to(depth)
    uv = pixel_grid(height, width, device=depth.device).to(depth).reshape(1, -1, 2).expand(batch, -1, -1)
    points = unproject_pixels(uv, depth.reshape(batch, -1), w2c, K).reshape(batch, height, width, 3)
    # contiguous: inductor's replication_pad2d_backward asserts the strides of a contiguous input (torch 2.13)
    padded = F.pad(points.permute(0, 3, 1, 2).contiguous(), (1, 1, 1, 1), mode="replicate").permute(0, 2, 3, 1)
    d_u = padded[:, 1:-1, 2:] - padded[:, 1:-1, :-2]
    d_v = padded[:, 2:, 1:-1] - padded[:, :-2, 1:-1]
    normals = F.normalize(torch.linalg.cross(d_u, d_v, dim=-1), dim=-1)
    to_camera = camera_centers(w2c)[:, None, None, :] - points
    facing = (normals * to_camera).sum(-1, keepdim=True)
    return torch.where(facing < 0, -normals, normals)


def normal_consistency_loss(normals: Tensor, pseudo_normals: Tensor, mask: Tensor | None = None) -> Tensor:
    """Eq. A.2: ``mean over M of ||N - N~||_2`` (per-pixel Euclidean norm, as the supplement states).

    Gradients reach both inputs: the training objective passes ``pseudo_normals`` attached, so the rendered
    normals and the rendered depth they come from are pulled toward agreement (R3DGS detaches them and
    supervises the normals alone). ``normals, pseudo_normals [B,H,W,3]``, ``mask [B,H,W,1]`` -> scalar.
    """
    _check_map("normals", normals, 3)
    if pseudo_normals.shape != normals.shape:
        raise ValueError(
            f"normals {tuple(normals.shape)} and pseudo_normals {tuple(pseudo_normals.shape)} must match"
        )
    distance = torch.linalg.vector_norm(normals - pseudo_normals, dim=-1, keepdim=True)
    return masked_mean(distance, mask)


def incident_light_loss(incident: Tensor, visibility: Tensor, mask: Tensor | None = None) -> Tensor:
    """Eq. A.3: ``mean over M of |clamp(L_in, 0, 1) - V_SH|``.

    Any matching shapes (per-Gaussian ``[N,1]`` or per-pixel ``[B,H,W,1]``); ``mask`` broadcastable.
    """
    if incident.shape != visibility.shape:
        raise ValueError(
            f"incident {tuple(incident.shape)} and visibility {tuple(visibility.shape)} must match"
        )
    return masked_mean((incident.clamp(0.0, 1.0) - visibility).abs(), mask)


def raytrace_visibility_loss(
    visibility_sh: Tensor, visibility_traced: Tensor, mask: Tensor | None = None
) -> Tensor:
    """Eq. A.7: ``mean over M of |V_SH - V_RT|``; ``V_RT`` (ray-traced) carries no gradient.

    Any matching shapes; ``mask`` broadcastable.
    """
    if visibility_sh.shape != visibility_traced.shape:
        raise ValueError(
            f"visibility_sh {tuple(visibility_sh.shape)} and visibility_traced "
            f"{tuple(visibility_traced.shape)} must match"
        )
    return masked_mean((visibility_sh - visibility_traced.detach()).abs(), mask)
