"""Relightable 3D Gaussians: parameters (:mod:`.model`), initial point clouds (:mod:`.init`), PLY I/O
(:mod:`.ply`)."""

from __future__ import annotations

from diamond_sss.gaussians.init import (
    EmptyVisualHullError,
    InitialPoints,
    VoxelHull,
    carve_visual_hull,
    initial_points,
    random_points_in_sphere,
    visual_hull_points,
)
from diamond_sss.gaussians.model import (
    NUM_VISIBILITY_SH,
    PARAM_SHAPES,
    GaussianModel,
    nearest_neighbor_scales,
    outward_normals,
)
from diamond_sss.gaussians.ply import base_color_to_sh_dc, export_ply, import_ply, load_points3d_ply
from diamond_sss.shading.sh import SH_C0

__all__ = [
    "NUM_VISIBILITY_SH",
    "PARAM_SHAPES",
    "SH_C0",
    "EmptyVisualHullError",
    "GaussianModel",
    "InitialPoints",
    "VoxelHull",
    "base_color_to_sh_dc",
    "carve_visual_hull",
    "export_ply",
    "import_ply",
    "initial_points",
    "load_points3d_ply",
    "nearest_neighbor_scales",
    "outward_normals",
    "random_points_in_sphere",
    "visual_hull_points",
]
