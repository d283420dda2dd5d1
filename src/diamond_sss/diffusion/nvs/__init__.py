"""Free3D-style novel-view diffusion (supplement Sec. C.2): ray-conditioned multi-view UNet on diffusers."""

from __future__ import annotations

from diamond_sss.diffusion.nvs.model import NVSBatch, NVSConfig, NVSModel, shared_noise
from diamond_sss.diffusion.nvs.rays import (
    harmonic_embedding,
    plucker_rays,
    ray_embedding,
    relative_spherical_pose,
    view_angle_degrees,
)

__all__ = [
    "NVSBatch",
    "NVSConfig",
    "NVSModel",
    "harmonic_embedding",
    "plucker_rays",
    "ray_embedding",
    "relative_spherical_pose",
    "shared_noise",
    "view_angle_degrees",
]
