"""One viewer frame: the browser's camera and the GUI's light and material settings -> an sRGB image.

Pure functions, independent of the web server. viser reports a camera as the rotation ``wxyz`` and position
``t`` of ``P_world = R P_camera + t`` with OpenCV camera axes (x right, y down, z forward), so the
world-to-camera matrix is ``[R^T | -R^T t]``; its field of view is vertical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from diamond_sss.data.conventions import intrinsics_from_fov
from diamond_sss.data.images import to_srgb8
from diamond_sss.evaluation.evaluate import DECOMPOSITION, decomposition_maps
from diamond_sss.evaluation.figures import to_display
from diamond_sss.scene.model import RelightableScene

CHANNELS = ("radiance", *DECOMPOSITION)
"""What the viewer can show: the shaded image or one map of the decomposition."""


@dataclass
class ViewSettings:
    """GUI state. Light on a sphere around the object: azimuth about world +z from +x, elevation above the
    xy-plane (degrees), distance in object radii; ``intensity`` is the light's grey RGB intensity. ``overrides``
    replace materials by constants (``RelightableScene.render``)."""

    azimuth_deg: float = 30.0
    elevation_deg: float = 30.0
    distance_radii: float = 4.0
    intensity: float = 1.0
    channel: str = "radiance"
    overrides: dict[str, float] = field(default_factory=dict)


def viser_camera_to_w2c(wxyz: np.ndarray, position: np.ndarray) -> Tensor:
    """OpenCV world-to-camera ``[4,4]`` of a viser camera (rotation quaternion ``wxyz``, position ``[3]``)."""
    w, x, y, z = (float(v) for v in np.asarray(wxyz) / np.linalg.norm(wxyz))
    rotation = torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = rotation.T
    w2c[:3, 3] = -rotation.T @ torch.as_tensor(np.asarray(position), dtype=torch.float64)
    return w2c.float()


def view_intrinsics(fov_y: float, aspect: float, height: int) -> tuple[Tensor, int, int]:
    """Pinhole ``K [3,3]`` (:func:`~diamond_sss.data.conventions.intrinsics_from_fov`, square pixels), width and
    height of the browser's view: vertical field of view ``fov_y`` (radians), aspect ratio ``width / height``,
    image height in pixels."""
    if not 0.0 < fov_y < math.pi:
        raise ValueError(f"the vertical field of view must be in (0, pi) radians, got {fov_y}")
    width = max(1, round(height * aspect))
    return intrinsics_from_fov(None, width, height, fov_y), width, height


def light_from_angles(center: Tensor, radius: float, settings: ViewSettings) -> Tensor:
    """World position ``[3]`` of the light: ``c + d r (cos e cos a, cos e sin a, sin e)``."""
    azimuth, elevation = math.radians(settings.azimuth_deg), math.radians(settings.elevation_deg)
    direction = torch.tensor(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ]
    )
    return center.detach().float().cpu() + settings.distance_radii * float(radius) * direction


@torch.no_grad()
def render_frame(
    scene: RelightableScene, w2c: Tensor, K: Tensor, width: int, height: int, settings: ViewSettings
) -> np.ndarray:
    """uint8 sRGB image ``[H,W,3]`` of ``settings.channel`` seen by ``w2c``, ``K`` (over black)."""
    if settings.channel not in CHANNELS:
        raise ValueError(f"unknown channel {settings.channel!r}; choose one of {', '.join(CHANNELS)}")
    device = scene.scene_center.device
    light = light_from_angles(scene.scene_center, float(scene.scene_radius), settings)
    render = scene.render(
        w2c[None].to(device),
        K[None].to(device),
        width,
        height,
        light[None].to(device),
        torch.full((1, 3), float(settings.intensity), device=device),
        overrides=settings.overrides or None,
    )
    if settings.channel == "radiance":
        return to_srgb8(render.radiance[0].cpu())
    image, linear = decomposition_maps(render)[settings.channel]
    return (to_display(image[0], linear=linear) * 255.0 + 0.5).astype(np.uint8)
