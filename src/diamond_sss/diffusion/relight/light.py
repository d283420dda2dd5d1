"""Light encoding: degree-2 SH code of the light direction in the source camera's frame, plus its distance."""

from __future__ import annotations

import torch
from torch import Tensor

from diamond_sss.shading.sh import light_sh_encoding


def light_code(light_positions: Tensor, w2c: Tensor, center: Tensor, radius: float) -> Tensor:
    """``[Y_0..8(R (p - c) / |p - c|), |p - c| / r]`` -> ``[..., 10]``.

    ``light_positions [...,3]`` world; ``w2c [...,4,4]`` (OpenCV) of the source camera, whose rotation ``R``
    expresses the direction in that camera's frame (x right, y down, z forward); ``center [3]`` and
    ``radius`` (world units) of the object's bounding sphere, so the distance is in object radii.
    """
    if light_positions.shape[-1] != 3:
        raise ValueError(f"light_positions must be [..., 3], got {tuple(light_positions.shape)}")
    if w2c.shape[-2:] != (4, 4):
        raise ValueError(f"w2c must be [..., 4, 4], got {tuple(w2c.shape)}")
    if radius <= 0:
        raise ValueError(f"radius must be positive, got {radius}")
    offset = light_positions - center.to(light_positions)
    distance = offset.norm(dim=-1, keepdim=True)
    if bool((distance < 1e-8).any()):
        raise ValueError("a light sits at the object's centre: its direction is undefined")
    direction_cam = (w2c[..., :3, :3].to(offset) @ offset.unsqueeze(-1)).squeeze(-1)
    return torch.cat([light_sh_encoding(direction_cam, degree=2), distance / radius], dim=-1)
