"""Depth below the lit surface, from a depth map rendered at the light (a translucent shadow map).

A point light at ``p`` sees the scene's bounding sphere (centre ``c``, radius ``r``) through a pinhole camera at
``p`` looking at ``c`` whose field of view just covers the sphere: ``tan(theta) = r' / sqrt(d^2 - r'^2)`` with
``d = |p - c|`` and ``r' = margin r``. With ``D(u)`` that camera's expected depth (``alpha > 1/2``, else no
surface), a point ``x`` projecting to ``u`` at depth ``z`` lies ``t = max(z - D(u), 0)`` below the first
surface the light meets: the distance light travels inside the object before reaching ``x``, which sets how
much of it survives there (``exp(-sigma_t t)`` in a homogeneous medium; Dachsbacher & Stamminger 2003). Unlike
a learnt visibility, ``t`` is computed from the geometry for any light, so it holds for lights never trained on.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from diamond_sss.data.conventions import (
    look_at_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    project_points,
    sample_bilinear,
)

COVERAGE_MARGIN = 1.05
"""The light camera's field of view covers the bounding sphere grown by this factor."""
MAX_HALF_ANGLE = math.radians(80.0)
"""Half field of view used when the light is inside (or nearly inside) the grown bounding sphere."""


@torch.no_grad()
def light_cameras(light_pos: Tensor, center: Tensor, radius: Tensor | float, size: int) -> tuple[Tensor, Tensor]:
    """Pinhole cameras at the lights looking at ``center``, square ``size`` px, covering the bounding sphere.

    ``light_pos [B, 3]``, ``center [3]`` (world), ``radius`` (scene units) -> ``w2c [B, 4, 4]`` (OpenCV) and
    ``K [B, 3, 3]`` (pixels, ``f = (size / 2) / tan(theta)``), on ``light_pos``'s device and dtype. No gradient.
    """
    if light_pos.dim() != 2 or light_pos.shape[-1] != 3:
        raise ValueError(f"light_pos must be [B, 3], got {tuple(light_pos.shape)}")
    if size <= 0:
        raise ValueError(f"the light depth map size must be positive, got {size}")
    center = center.to(light_pos)
    distance = (light_pos - center).norm(dim=-1)
    grown = COVERAGE_MARGIN * torch.as_tensor(radius, dtype=light_pos.dtype, device=light_pos.device)
    half_angle = torch.asin((grown / distance).clamp(max=1.0)).clamp(max=MAX_HALF_ANGLE)
    focal = 0.5 * size / torch.tan(half_angle)
    K = torch.zeros(light_pos.shape[0], 3, 3, dtype=light_pos.dtype, device=light_pos.device)
    K[:, 0, 0], K[:, 1, 1], K[:, :2, 2], K[:, 2, 2] = focal, focal, 0.5 * size, 1.0
    w2c = opengl_c2w_to_opencv_w2c(look_at_opengl_c2w(light_pos, center)).to(light_pos)
    return w2c, K


def depth_below_surface(points: Tensor, w2c: Tensor, K: Tensor, depth: Tensor, alpha: Tensor) -> Tensor:
    """``t = max(z - D(u), 0)`` of ``points [N, 3]`` in each light camera ``(w2c [B, 4, 4], K [B, 3, 3])``.

    ``depth``, ``alpha [B, S, S, 1]``: the light camera's expected depth and opacity. Pixels with
    ``alpha <= 1/2`` hold no surface and points outside the map or behind the camera get ``t = 0``.
    Returns ``[B, N, 1]`` in scene units.
    """
    batch = w2c.shape[0]
    uv, z = project_points(points.expand(batch, *points.shape), w2c, K)
    size = depth.shape[1]
    covered = alpha[..., 0] > 0.5
    far = (z.detach().amax() if z.numel() else z.new_zeros(())) + 1.0  # behind every point
    surface = torch.where(covered, depth[..., 0], far.expand_as(depth[..., 0]))
    first_hit = sample_bilinear(surface, uv)
    inside = (z > 0) & (uv >= 0).all(-1) & (uv <= size).all(-1)
    return torch.where(inside, (z - first_hit).clamp_min(0.0), torch.zeros_like(z)).unsqueeze(-1)


class LightMapCache:
    """Light depth maps reused across training steps.

    A light's map (depth and alpha, ``[1, S, S, 1]``) is rendered at its first use in each window of ``every``
    steps and reused for the rest of the window: a cue without gradient, from a geometry that moves little in a
    few steps. :meth:`start_step` opens a window every ``every`` steps; :meth:`clear` ends one early (the trainer
    clears at each checkpoint, so that a run resumed there renders what the uninterrupted run renders).
    """

    def __init__(self, every: int) -> None:
        if every < 1:
            raise ValueError(f"a light map is reused for at least 1 step, got every={every}")
        self.every = every
        self._maps: dict[Hashable, tuple[Tensor, Tensor]] = {}

    def __len__(self) -> int:
        return len(self._maps)

    def start_step(self, step: int) -> None:
        """Called before each training step: a new window starts at every multiple of ``every``."""
        if step % self.every == 0:
            self.clear()

    def clear(self) -> None:
        self._maps.clear()

    def maps(self, keys: Sequence[Hashable], render: Callable[[list[int]], tuple[Tensor, Tensor]]
             ) -> tuple[Tensor, Tensor]:
        """Depth and alpha maps ``[B, S, S, 1]`` of the batch's lights, named by ``keys`` (one per image).

        ``render(rows)`` renders the maps of the batch rows ``rows`` (``[len(rows), S, S, 1]`` each); it is called
        once, for the first row of every light not in the cache.
        """
        missing: dict[Hashable, int] = {}
        for row, key in enumerate(keys):
            if key not in self._maps and key not in missing:
                missing[key] = row
        if missing:
            depth, alpha = render(list(missing.values()))
            for index, key in enumerate(missing):
                self._maps[key] = (depth[index:index + 1], alpha[index:index + 1])
        return (torch.cat([self._maps[key][0] for key in keys]), torch.cat([self._maps[key][1] for key in keys]))


class CachedLights(NamedTuple):
    """A batch's lights in a :class:`LightMapCache`: the cache and one key per image (e.g. the light's index)."""

    cache: LightMapCache
    keys: Sequence[Hashable]
