"""EWA projection of 3D Gaussians to the image plane, with gsplat's (1.5.3) conventions.

Pure, differentiable functions of plain tensors. Cameras are OpenCV world-to-camera ``viewmats [B,4,4]``
and pixel-unit intrinsics ``Ks [B,3,3]`` (see :mod:`diamond_sss.data.conventions`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

ALPHA_THRESHOLD = 1.0 / 255.0
"""Contributions with ``alpha`` below this are dropped (gsplat's ``ALPHA_THRESHOLD``)."""

MAX_EXTENT_SIGMAS = 3.33
"""Upper bound of the screen-space extent in standard deviations (gsplat's ``extend``)."""


@dataclass
class ProjectedGaussians:
    """Screen-space Gaussians for ``B`` cameras and ``N`` Gaussians (entries with ``radii == 0`` are culled).

    Attributes:
        means2d: ``[B,N,2]`` pixel coordinates ``(u, v)`` of the projected centres (pixel centres at +0.5).
        conics: ``[B,N,3]`` upper triangle ``(a, b, c)`` of the inverse 2D covariance, in 1/pixel^2.
        depths: ``[B,N]`` camera-space z of the centres (scene units).
        radii: ``[B,N,2]`` int32 half-extents ``(r_x, r_y)`` of the screen-space bounding box in pixels.
        covars2d: ``[B,N,3]`` upper triangle of the dilated 2D covariance, in pixel^2.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    covars2d: Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices of (not necessarily unit) ``wxyz`` quaternions. ``[...,4] -> [...,3,3]``."""
    w, x, y, z = (quats / quats.norm(dim=-1, keepdim=True)).unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*quats.shape[:-1], 3, 3)


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World-space covariance ``Sigma = R S S^T R^T`` with ``S = diag(scales)``. ``[...,4],[...,3] -> [...,3,3]``."""
    m = quat_to_rotmat(quats) * scales[..., None, :]
    return m @ m.transpose(-1, -2)


def perspective_jacobian(means_cam: Tensor, Ks: Tensor, width: int, height: int) -> Tensor:
    """Jacobian ``J [B,N,2,3]`` of the pinhole projection at camera-space points ``means_cam [B,N,3]``.

    ``J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]`` where ``tx/z, ty/z`` are ``x/z, y/z`` clamped to
    the field of view widened by 30 % (gsplat's ``persp_proj``), which keeps off-screen Gaussians bounded.
    """
    fx, fy = Ks[:, None, 0, 0], Ks[:, None, 1, 1]
    cx, cy = Ks[:, None, 0, 2], Ks[:, None, 1, 2]
    x, y, z = means_cam.unbind(-1)
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    tx = z * torch.minimum(
        (width - cx) / fx + 0.3 * tan_fovx, torch.maximum(-(cx / fx + 0.3 * tan_fovx), x / z)
    )
    ty = z * torch.minimum(
        (height - cy) / fy + 0.3 * tan_fovy, torch.maximum(-(cy / fy + 0.3 * tan_fovy), y / z)
    )
    zeros = torch.zeros_like(z)
    rows = (fx / z, zeros, -fx * tx / (z * z), zeros, fy / z, -fy * ty / (z * z))
    return torch.stack(rows, dim=-1).reshape(*z.shape, 2, 3)


def screen_radii(covars2d: Tensor, opacities: Tensor) -> Tensor:
    """Opacity-aware bounding-box half-extents in pixels, int32 ``[...,2]`` (not differentiable).

    ``r_x = ceil(e sqrt(Sigma_xx))``, ``r_y = ceil(e sqrt(Sigma_yy))`` with
    ``e = min(3.33, sqrt(2 ln(255 o)))``: outside this box ``o exp(-q/2) < 1/255``, so the box holds every
    contribution that survives the cut-off. Gaussians with ``o < 1/255`` get radius 0.
    """
    with torch.no_grad():
        opacities = opacities.float()
        visible = opacities >= ALPHA_THRESHOLD
        extent = torch.sqrt(2.0 * torch.log(opacities.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
        extent = extent.clamp_max(MAX_EXTENT_SIGMAS)
        sigmas = torch.stack([covars2d[..., 0], covars2d[..., 2]], dim=-1).float().clamp_min(0.0).sqrt()
        radii = torch.ceil(extent[..., None] * sigmas)
        return torch.where(visible[..., None], radii, 0.0).to(torch.int32)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
) -> ProjectedGaussians:
    """EWA splatting projection ``Sigma_2d = J W Sigma W^T J^T + eps2d I`` of ``N`` Gaussians into ``B`` cameras.

    ``means [N,3]``, ``quats [N,4]`` (wxyz), ``scales [N,3]`` (world units), ``opacities [N]``,
    ``viewmats [B,4,4]`` (OpenCV w2c), ``Ks [B,3,3]``. A Gaussian is culled (``radii = 0``) when its centre is
    outside ``[near_plane, far_plane]`` in camera z, its dilated covariance is degenerate, its opacity is below
    1/255, or its bounding box misses the image. Culled entries hold finite placeholder values.
    """
    rot, trans = viewmats[:, None, :3, :3], viewmats[:, None, :3, 3]
    means_cam = (rot @ means[None, :, :, None]).squeeze(-1) + trans
    depths = means_cam[..., 2]
    in_range = (depths >= near_plane) & (depths <= far_plane)
    safe_cam = torch.where(in_range[..., None], means_cam, torch.ones_like(means_cam))
    covars_cam = rot @ covariance_3d(quats, scales)[None] @ rot.transpose(-1, -2)
    jac = perspective_jacobian(safe_cam, Ks, width, height)
    cov2d = jac @ covars_cam @ jac.transpose(-1, -2)
    a = cov2d[..., 0, 0] + eps2d
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    valid = in_range & (det > 0)
    safe_det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / safe_det, -b / safe_det, a / safe_det], dim=-1)
    covars2d = torch.stack([a, b, c], dim=-1)

    x, y, z = safe_cam.unbind(-1)
    u = Ks[:, None, 0, 0] * x / z + Ks[:, None, 0, 2]
    v = Ks[:, None, 1, 1] * y / z + Ks[:, None, 1, 2]
    means2d = torch.stack([u, v], dim=-1)

    radii = screen_radii(covars2d.detach(), opacities.detach().expand_as(depths))
    with torch.no_grad():
        r = radii.to(means2d.dtype)
        on_screen = (
            (means2d[..., 0] + r[..., 0] > 0)
            & (means2d[..., 0] - r[..., 0] < width)
            & (means2d[..., 1] + r[..., 1] > 0)
            & (means2d[..., 1] - r[..., 1] < height)
        )
        radii = torch.where((valid & on_screen)[..., None], radii, 0)
    return ProjectedGaussians(means2d=means2d, conics=conics, depths=depths, radii=radii, covars2d=covars2d)


def tile_grid_shape(width: int, height: int, tile_size: int) -> tuple[int, int]:
    """Number of tiles ``(tiles_x, tiles_y)`` covering a ``width x height`` image."""
    return math.ceil(width / tile_size), math.ceil(height / tile_size)
