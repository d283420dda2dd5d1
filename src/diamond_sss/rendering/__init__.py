"""Gaussian rasterization: one entry point, :func:`rasterize`, with a CUDA (gsplat) and a CPU backend."""

from __future__ import annotations

from diamond_sss.rendering.projection import (
    ProjectedGaussians,
    covariance_3d,
    project_gaussians,
    quat_to_rotmat,
)
from diamond_sss.rendering.rasterize import RasterOutput, rasterize

__all__ = [
    "ProjectedGaussians",
    "RasterOutput",
    "covariance_3d",
    "project_gaussians",
    "quat_to_rotmat",
    "rasterize",
]
