"""The geometry-source interface and the math shared by its implementations."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.errors import DataError

MASK_THRESHOLD = 0.5
"""A pixel belongs to the object where its mask exceeds this."""


class GeometryError(DataError):
    """No usable geometry for a view (missing maps, run folder or model path): bad input, a :class:`DataError`."""


@dataclass
class GeometryMaps:
    """Conditioning geometry of one view at the image's resolution.

    Attributes:
        nearness: normalised nearness ``[H,W,1]`` in [0, 1] over the mask (1 = nearest, 0 outside).
        normals: unit normals ``[H,W,3]`` in the OpenCV camera frame (x right, y down, z forward); 0 outside.
        mask: object mask ``[H,W,1]`` in [0, 1].
        depth: metric camera z ``[H,W,1]`` in world units (0 = background), or None for sources that only
            know relative depth (Depth Anything, Marigold).
    """

    nearness: Tensor
    normals: Tensor
    mask: Tensor
    depth: Tensor | None = None


class GeometrySource(ABC):
    """Produces :class:`GeometryMaps` for a view of a data set, given its source image and mask."""

    @abstractmethod
    def maps(self, dataset: OLATDataset, view: int, image: Tensor, mask: Tensor) -> GeometryMaps:
        """Geometry of ``view``; ``image [H,W,3]`` linear radiance and ``mask [H,W,1]`` of the source photo."""

    @abstractmethod
    def key(self) -> dict:
        """JSON identity of the source (kind and content hash of its weights), part of cache keys through
        :meth:`view_key`."""

    def view_key(self, dataset: OLATDataset, view: int) -> dict:
        """JSON identity of the maps of ``view`` of ``dataset`` in cache keys: :meth:`key`, plus the content hash of
        what the source reads from the data besides the view's image, mask and camera (which the keys hold)."""
        return self.key()


def normals_from_nearness(nearness: Tensor, mask: Tensor) -> Tensor:
    """Camera-space normals of the height field ``h = s * nearness`` seen head-on: ``n ~ (-h_x, -h_y, -1)``.

    ``s`` is the object's pixel extent ``sqrt(mask area)``, so a nearness ramp of 1 across the object reads
    as a 45-degree slope. An approximation for sources that only give relative depth. ``[H,W,1] -> [H,W,3]``.
    """
    keep = (mask > 0.5).to(nearness.dtype)
    scale = keep.sum().sqrt().clamp_min(1.0)
    height = nearness[..., 0] * scale
    padded = F.pad(height[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    grad_x = (padded[1:-1, 2:] - padded[1:-1, :-2]) * 0.5
    grad_y = (padded[2:, 1:-1] - padded[:-2, 1:-1]) * 0.5
    normals = torch.stack([-grad_x, -grad_y, -torch.ones_like(grad_x)], dim=-1)
    return F.normalize(normals, dim=-1) * keep


def normalized_nearness(disparity: Tensor, mask: Tensor) -> Tensor:
    """Scale a disparity-like map ``[...,H,W,1]`` to [0, 1] over ``mask > 0.5`` (0 outside; 1 = nearest)."""
    keep = mask > MASK_THRESHOLD
    flat_d = disparity.flatten(-3)
    flat_k = keep.flatten(-3)
    big = torch.finfo(disparity.dtype).max
    low = torch.where(flat_k, flat_d, big).amin(-1)
    high = torch.where(flat_k, flat_d, -big).amax(-1)
    shape = disparity.shape[:-3] + (1, 1, 1)
    low, high = low.reshape(shape), high.reshape(shape)
    scaled = (disparity - low) / (high - low).clamp_min(1e-8)
    return torch.where(keep, scaled.clamp(0.0, 1.0), torch.zeros_like(scaled))


def depth_to_nearness(depth: Tensor, mask: Tensor) -> Tensor:
    """Camera-z depth ``[...,H,W,1]`` (0 = background) -> normalised nearness (see module doc)."""
    keep = (mask > MASK_THRESHOLD) & (depth > 0)
    disparity = torch.where(keep, 1.0 / depth.clamp_min(1e-8), torch.zeros_like(depth))
    return normalized_nearness(disparity, keep.to(depth.dtype))


def world_to_camera_normals(normals_world: Tensor, w2c: Tensor) -> Tensor:
    """Rotate world normals ``[B,H,W,3]`` into each camera's OpenCV frame with ``w2c [B,4,4]``."""
    rotated = torch.einsum("bij,bhwj->bhwi", w2c[:, :3, :3].to(normals_world), normals_world)
    return F.normalize(rotated, dim=-1, eps=1e-8)
