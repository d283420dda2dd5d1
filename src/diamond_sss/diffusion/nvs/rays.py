"""Camera conditioning of the novel-view model: Plucker rays, harmonic embedding, relative spherical pose.

All cameras are OpenCV world-to-camera matrices ``w2c [...,4,4]`` and pixel intrinsics ``K [...,3,3]``
(see :mod:`diamond_sss.data.conventions`). Rays are expressed in the *reference* camera's frame, so the
conditioning is invariant to the choice of world frame (Free3D, Zheng & Vedaldi 2024).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from diamond_sss.data.conventions import camera_centers, pixel_grid

RAY_CHANNELS = 6
HARMONIC_FREQUENCIES = 6
RAY_EMBEDDING_CHANNELS = RAY_CHANNELS * (2 * HARMONIC_FREQUENCIES + 1)  # 78
RELATIVE_POSE_CHANNELS = 4


def _check_matrix(name: str, tensor: Tensor, size: int) -> None:
    if tensor.shape[-2:] != (size, size):
        raise ValueError(f"{name} must have shape [...,{size},{size}], got {tuple(tensor.shape)}")


def relative_w2c(target_w2c: Tensor, reference_w2c: Tensor) -> Tensor:
    """Target camera expressed in the reference camera's frame: ``w2c_t @ inv(w2c_r)``. ``[...,4,4]``.

    Inverses here use ``linalg.inv_ex``: ``linalg.inv`` checks for singular matrices on the host, which makes every
    CUDA training step wait for the GPU.
    """
    _check_matrix("target_w2c", target_w2c, 4)
    _check_matrix("reference_w2c", reference_w2c, 4)
    return target_w2c @ torch.linalg.inv_ex(reference_w2c).inverse


def plucker_rays(target_w2c: Tensor, reference_w2c: Tensor, K: Tensor, height: int, width: int) -> Tensor:
    """Per-pixel Plucker coordinates ``(d, c x d)`` of the target camera's rays in the reference frame.

    ``d = normalize(R^T K^-1 [u, v, 1])`` through pixel centres ``(j + 0.5, i + 0.5)`` and ``c`` the target
    camera centre, both in reference-camera coordinates (units of the world). Shapes ``[...,4,4]``,
    ``[...,4,4]``, ``[...,3,3]`` -> ``[...,6,H,W]``.
    """
    _check_matrix("K", K, 3)
    if height < 1 or width < 1:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    rel = relative_w2c(target_w2c, reference_w2c)
    K = K.to(rel.dtype)
    uv = pixel_grid(height, width, device=K.device).to(K.dtype).reshape(-1, 2)
    pix = torch.cat([uv, torch.ones_like(uv[:, :1])], dim=-1)  # [HW,3]
    cam_dirs = pix @ torch.linalg.inv_ex(K).inverse.transpose(-1, -2)  # [...,HW,3]
    dirs = cam_dirs @ rel[..., :3, :3]  # R^T d for row vectors
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    center = camera_centers(rel)[..., None, :].expand_as(dirs)
    moment = torch.linalg.cross(center, dirs, dim=-1)
    rays = torch.cat([dirs, moment], dim=-1)  # [...,HW,6]
    return rays.transpose(-1, -2).reshape(*rays.shape[:-2], RAY_CHANNELS, height, width)


def harmonic_embedding(x: Tensor, n_frequencies: int = HARMONIC_FREQUENCIES, dim: int = -1) -> Tensor:
    """PyTorch3D harmonic embedding along ``dim``: ``[sin(x_i 2^k), cos(x_i 2^k), x_i]``.

    Channel layout (as in Free3D's checkpoint): all sines (input-major, frequency-minor), then all cosines,
    then the input itself; ``C -> C (2 n + 1)`` channels (6 -> 78 for 6 frequencies).
    """
    x = x.movedim(dim, -1)
    freqs = 2.0 ** torch.arange(n_frequencies, device=x.device, dtype=x.dtype)
    phase = (x[..., None] * freqs).flatten(-2)
    return torch.cat([phase.sin(), phase.cos(), x], dim=-1).movedim(-1, dim)


def ray_embedding(target_w2c: Tensor, reference_w2c: Tensor, K: Tensor, height: int, width: int) -> Tensor:
    """Harmonic-embedded Plucker rays, ``[...,78,H,W]`` (the ray-conditioning input of every ResNet block)."""
    return harmonic_embedding(plucker_rays(target_w2c, reference_w2c, K, height, width), dim=-3)


def spherical_coordinates(w2c: Tensor, center: Tensor | None = None) -> Tensor:
    """Camera centre in spherical coordinates about ``center`` (world z up): ``(polar, azimuth, radius)``.

    Polar angle from +z in radians, azimuth ``atan2(y, x)``. ``[...,4,4] -> [...,3]``.
    """
    c = camera_centers(w2c)
    if center is not None:
        c = c - center
    xy = c[..., 0].square() + c[..., 1].square()
    radius = (xy + c[..., 2].square()).sqrt()
    polar = torch.atan2(xy.sqrt(), c[..., 2])
    azimuth = torch.atan2(c[..., 1], c[..., 0])
    return torch.stack([polar, azimuth, radius], dim=-1)


def relative_spherical_pose(
    target_w2c: Tensor, reference_w2c: Tensor, center: Tensor | None = None
) -> Tensor:
    """Zero123 / Free3D global pose token ``(d polar, sin d azim, cos d azim, d radius)``, ``[...,4]``."""
    t = spherical_coordinates(target_w2c, center)
    r = spherical_coordinates(reference_w2c, center)
    d = t - r
    azimuth = torch.remainder(d[..., 1], 2 * math.pi)
    return torch.stack([d[..., 0], azimuth.sin(), azimuth.cos(), d[..., 2]], dim=-1)


def view_angle_degrees(target_w2c: Tensor, reference_w2c: Tensor, center: Tensor | None = None) -> Tensor:
    """Angle between the two cameras' centres seen from ``center`` (default: world origin), degrees."""
    a = camera_centers(target_w2c)
    b = camera_centers(reference_w2c)
    if center is not None:
        a, b = a - center, b - center
    cos = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(1e-12)
    return torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))
