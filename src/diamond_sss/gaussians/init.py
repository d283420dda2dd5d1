"""Initial point clouds for the Gaussians.

The order of preference (:func:`initial_points`): the data set's ``points3d.ply`` when there is one,
else a visual hull carved from the training masks (robust for sparse views), else uniform random
points in the scene's bounding sphere.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import project_points, sample_bilinear
from diamond_sss.errors import data_error
from diamond_sss.gaussians.model import SCALE_NEIGHBOURS
from diamond_sss.gaussians.ply import load_points3d_ply
from diamond_sss.utils import rng

logger = logging.getLogger(__name__)


class EmptyVisualHullError(RuntimeError):
    """No voxel survived the carving: the masks, cameras and bounds do not agree."""


@dataclass
class InitialPoints:
    """An initial point cloud and where it came from (``"points3d"``, ``"visual_hull"`` or ``"random"``).

    ``colors`` are linear RGB in ``[0,1]``; ``colors`` and ``normals`` are ``None`` when unknown.
    """

    points: Tensor
    colors: Tensor | None
    normals: Tensor | None
    source: str


def random_points_in_sphere(
    center: Tensor, radius: float, n: int, generator: torch.Generator | None = None
) -> Tensor:
    """``n`` points uniform in the ball ``|x - center| <= radius``. ``[3] -> [n,3]``.

    Direction from a normalised Gaussian vector, distance ``radius * u^(1/3)`` with ``u ~ U[0,1)``.
    """
    if radius <= 0 or n <= 0:
        raise ValueError(f"need radius > 0 and n > 0, got radius={radius}, n={n}")
    center = torch.as_tensor(center, dtype=torch.float32)
    directions = F.normalize(rng.randn(n, 3, generator=generator, device=center.device), dim=-1)
    distances = radius * rng.rand(n, 1, generator=generator, device=center.device).pow(1.0 / 3.0)
    return directions * distances + center


@dataclass
class VoxelHull:
    """A carved occupancy grid of ``resolution^3`` cubes of side ``voxel_size`` starting at ``origin``.

    Voxel ``(i, j, k)`` has its centre at ``origin + (i + 0.5, j + 0.5, k + 0.5) * voxel_size``
    (``i`` along world x).
    """

    occupied: Tensor
    origin: Tensor
    voxel_size: float

    def centers(self, index: Tensor) -> Tensor:
        """World centres of voxels given as integer indices ``[M,3]``."""
        return self.origin + (index.to(self.origin.dtype) + 0.5) * self.voxel_size

    def surface(self) -> Tensor:
        """``[R,R,R]`` bool: occupied voxels with at least one empty (or out-of-grid) 6-neighbour."""
        padded = F.pad(self.occupied[None, None].float(), (1, 1, 1, 1, 1, 1))[0, 0] > 0.5
        core = (slice(1, -1),) * 3
        interior = self.occupied.clone()
        for axis in range(3):
            for shift in (slice(None, -2), slice(2, None)):
                neighbour = list(core)
                neighbour[axis] = shift
                interior &= padded[tuple(neighbour)]
        return self.occupied & ~interior


def carve_visual_hull(
    masks: Tensor,
    w2c: Tensor,
    K: Tensor,
    bounds_center: Tensor,
    bounds_radius: float,
    *,
    resolution: int = 64,
    min_views_fraction: float = 0.5,
    mask_tolerance_views: int = 0,
    mask_threshold: float = 0.5,
) -> VoxelHull:
    """Space carving: the voxels inside the bounding sphere whose centres project into the foreground.

    For each voxel centre ``x`` and view ``v``: ``x`` is *seen* by ``v`` when it lies in front of the
    camera (``z > 0``) and projects inside the image; the mask is sampled bilinearly there (pixel
    centres at ``+0.5``) and ``x`` is *inside* when the value is ``>= mask_threshold``.
    A voxel survives when

    * it is seen by at least ``max(1, ceil(min_views_fraction * V))`` views (voxels no camera
      constrains are dropped rather than kept), and
    * at most ``mask_tolerance_views`` of the views that see it put it in the background.

    Views that do not see a voxel do not carve it: with sparse views, or cameras that crop the
    object, a partial view never removes geometry outside its frame. ``mask_tolerance_views > 0``
    tolerates noisy masks at the price of a fatter hull.

    Args:
        masks: ``[V,H,W]`` (or ``[V,H,W,1]``) foreground masks in ``[0,1]``, one per camera view (the
            masks of one view under other lights add nothing but weight in ``min_views_fraction``).
        w2c: ``[V,4,4]`` OpenCV world-to-camera matrices.
        K: ``[V,3,3]`` pixel intrinsics.
        bounds_center: ``[3]`` centre of the scene's bounding sphere.
        bounds_radius: its radius (scene units); the grid is the sphere's bounding cube.
        resolution: voxels per side.
    """
    if masks.ndim == 4 and masks.shape[-1] == 1:
        masks = masks[..., 0]
    if masks.ndim != 3:
        raise ValueError(f"masks must have shape [V,H,W] or [V,H,W,1], got {tuple(masks.shape)}")
    num_views, height, width = masks.shape
    if w2c.shape != (num_views, 4, 4) or K.shape != (num_views, 3, 3):
        raise ValueError(
            f"expected w2c [{num_views},4,4] and K [{num_views},3,3] for {num_views} masks, "
            f"got {tuple(w2c.shape)} and {tuple(K.shape)}"
        )
    if bounds_radius <= 0 or resolution < 2:
        raise ValueError(f"need bounds_radius > 0 and resolution >= 2, got {bounds_radius}, {resolution}")
    if not 0.0 <= min_views_fraction <= 1.0 or mask_tolerance_views < 0:
        raise ValueError(
            f"need 0 <= min_views_fraction <= 1 and mask_tolerance_views >= 0, "
            f"got {min_views_fraction}, {mask_tolerance_views}"
        )
    device = masks.device
    center = torch.as_tensor(bounds_center, dtype=torch.float32, device=device)
    voxel_size = 2.0 * bounds_radius / resolution
    origin = center - bounds_radius
    steps = (torch.arange(resolution, device=device, dtype=torch.float32) + 0.5) * voxel_size
    grid = torch.stack(torch.meshgrid(steps, steps, steps, indexing="ij"), dim=-1) + origin
    in_bounds = (grid - center).norm(dim=-1) <= bounds_radius + 0.5 * math.sqrt(3.0) * voxel_size
    points = grid[in_bounds]

    seen = torch.zeros(points.shape[0], dtype=torch.int32, device=device)
    outside = torch.zeros_like(seen)
    masks = masks.float()
    for view in range(num_views):
        uv, z = project_points(points, w2c[view].float().to(device), K[view].float().to(device))
        in_image = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= width) & (uv[:, 1] >= 0) & (uv[:, 1] <= height)
        sampled = sample_bilinear(masks[view][None], uv[None])[0]
        seen += in_image.int()
        outside += (in_image & (sampled < mask_threshold)).int()

    min_views = max(1, math.ceil(min_views_fraction * num_views))
    survives = (seen >= min_views) & (outside <= mask_tolerance_views)
    occupied = torch.zeros(resolution, resolution, resolution, dtype=torch.bool, device=device)
    occupied[in_bounds] = survives
    return VoxelHull(occupied=occupied, origin=origin, voxel_size=voxel_size)


def visual_hull_points(
    masks: Tensor,
    w2c: Tensor,
    K: Tensor,
    bounds_center: Tensor,
    bounds_radius: float,
    *,
    resolution: int = 64,
    num_points: int = 100_000,
    min_views_fraction: float = 0.5,
    mask_tolerance_views: int = 0,
    generator: torch.Generator | None = None,
) -> Tensor:
    """``num_points`` points sampled in the visual hull of ``masks`` (:func:`carve_visual_hull`). ``[M,3]``.

    Surface voxels (survivors with a carved 6-neighbour) come first, in random order, then interior
    voxels; the first ``num_points`` voxels of that order are used (cycling through it when there are
    fewer voxels than points), each point jittered uniformly inside its voxel. Seeded by ``generator``.

    Raises:
        EmptyVisualHullError: when no voxel survives.
    """
    if num_points <= 0:
        raise ValueError(f"num_points must be positive, got {num_points}")
    hull = carve_visual_hull(
        masks,
        w2c,
        K,
        bounds_center,
        bounds_radius,
        resolution=resolution,
        min_views_fraction=min_views_fraction,
        mask_tolerance_views=mask_tolerance_views,
    )
    surface = hull.surface()
    surface_index = surface.nonzero()
    interior_index = (hull.occupied & ~surface).nonzero()
    if surface_index.shape[0] == 0:
        raise EmptyVisualHullError(
            f"the visual hull is empty: no voxel of a {resolution}^3 grid in the sphere of radius "
            f"{bounds_radius} around {torch.as_tensor(bounds_center).tolist()} survives carving by "
            f"{masks.shape[0]} masks (check the masks, the camera poses and the scene bounds)"
        )
    def shuffled(index: Tensor) -> Tensor:
        return index[rng.randperm(index.shape[0], generator=generator, device=index.device)]

    order = torch.cat([shuffled(surface_index), shuffled(interior_index)])
    chosen = order[torch.arange(num_points, device=order.device) % order.shape[0]]
    jitter = rng.rand(num_points, 3, generator=generator, device=order.device) - 0.5
    return hull.centers(chosen) + jitter * hull.voxel_size


def initial_points(
    *,
    num_points: int,
    bounds_center: Tensor,
    bounds_radius: float,
    points3d_path: str | Path | None = None,
    masks: Tensor | None = None,
    w2c: Tensor | None = None,
    K: Tensor | None = None,
    hull_resolution: int = 64,
    generator: torch.Generator | None = None,
) -> InitialPoints:
    """The initial cloud: ``points3d_path`` if it exists, else the visual hull of ``masks`` (seen by
    ``w2c``, ``K``), else ``num_points`` random points in the bounding sphere. Each fallback is logged
    as a warning with its reason. ``num_points`` does not apply to a ``points3d.ply``, which must hold more than
    :data:`~diamond_sss.gaussians.model.SCALE_NEIGHBOURS` points (:class:`DataError` naming it otherwise)."""
    if points3d_path is not None and Path(points3d_path).is_file():
        points, colors, normals = load_points3d_ply(points3d_path)
        if points.shape[0] <= SCALE_NEIGHBOURS:
            raise data_error(points3d_path, f"{points.shape[0]} points; the initial Gaussians need at least "
                             f"{SCALE_NEIGHBOURS + 1} (their scales come from {SCALE_NEIGHBOURS} nearest neighbours)")
        return InitialPoints(points, colors, normals, "points3d")
    if masks is not None and w2c is not None and K is not None:
        try:
            points = visual_hull_points(
                masks,
                w2c,
                K,
                bounds_center,
                bounds_radius,
                resolution=hull_resolution,
                num_points=num_points,
                generator=generator,
            )
            return InitialPoints(points, None, None, "visual_hull")
        except EmptyVisualHullError as error:
            logger.warning("%s; falling back to random points in the scene bounds", error)
    else:
        logger.warning("no points3d.ply and no masks: initialising from random points in the scene bounds")
    points = random_points_in_sphere(bounds_center, bounds_radius, num_points, generator)
    return InitialPoints(points, None, None, "random")
