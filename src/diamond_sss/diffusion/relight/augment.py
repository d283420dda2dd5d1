"""Training augmentations of relighting batches that are exact symmetries of light transport.

- mirror: flipping the image left-right is the reflection ``x -> -x`` of the camera frame (OpenCV, x right),
  so the source and target images, the maps, the normals' x component and the lights' x direction are all
  mirrored together;
- exposure and tint: light transport is linear in the light's power, so scaling the source and the target's
  linear radiance by the same gain ``k_c = 2^(e u) exp(t v_c)`` (``u, v_c ~ U(-1, 1)``) keeps a valid pair
  (clamped to [0, 1] like a camera's range). It shows the model objects of other brightness and colour than
  the four fine-tuning objects.
- colour permutation: with white lights, the red, green and blue images are three independent renderings (one per
  channel's albedo and scattering coefficients), so permuting the channels of source and target together gives
  the exact pair of an object whose material has its coefficients permuted (a green "skin", a red "jade"). It
  breaks the tie between shape and material colour in four fine-tuning objects (each shape has one material).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from diamond_sss.diffusion.relight.conditioning import image_to_model, model_to_image
from diamond_sss.diffusion.relight.config import RelightAugmentConfig
from diamond_sss.diffusion.relight.hint import direction_from_code
from diamond_sss.shading.sh import light_sh_encoding
from diamond_sss.utils.device import to_device

SOURCE_CHANNELS = slice(0, 3)
"""The source image inside a conditioning image ``[B,8,R,R]``."""
CONDITIONING_NORMAL_X = 4
"""Camera-space normal x inside a conditioning image."""
MAPS_NORMAL_X = 1
"""Camera-space normal x inside the 5 non-image maps (nearness, normals, mask)."""


def mirror_code(code: Tensor) -> Tensor:
    """Light code ``[...,10]`` of the light mirrored by ``x -> -x`` in the camera frame."""
    direction, distance = direction_from_code(code)
    mirrored = torch.cat([-direction[..., :1], direction[..., 1:]], dim=-1)
    return torch.cat([light_sh_encoding(mirrored, degree=2), distance], dim=-1)


def mirror_batch(batch: dict[str, Tensor], chosen: Tensor) -> dict[str, Tensor]:
    """``batch`` (see ``RelightViews.batch``) with the pairs where ``chosen [B]`` (bool) mirrored left-right."""
    where = chosen[:, None, None, None]
    out = dict(batch)
    for key in ("conditioning", "target", "source", "maps"):
        flipped = batch[key].flip(-1)
        normal_x = CONDITIONING_NORMAL_X if key == "conditioning" else MAPS_NORMAL_X if key == "maps" else None
        if normal_x is not None:
            flipped = flipped.clone()
            flipped[:, normal_x] = -flipped[:, normal_x]
        out[key] = torch.where(where, flipped, batch[key])
    for key in ("target_code", "source_code"):
        out[key] = torch.where(chosen[:, None], mirror_code(batch[key]), batch[key])
    return out


def map_images(batch: dict[str, Tensor], transform: Callable[[Tensor], Tensor]) -> dict[str, Tensor]:
    """``batch`` with ``transform`` applied to its source and target images (model space ``[B,3,R,R]``), the
    conditioning's copy of the source included."""
    out = dict(batch)
    out["source"] = transform(batch["source"])
    out["target"] = transform(batch["target"])
    conditioning = batch["conditioning"].clone()
    conditioning[:, SOURCE_CHANNELS] = transform(batch["conditioning"][:, SOURCE_CHANNELS])
    out["conditioning"] = conditioning
    return out


def scale_radiance(batch: dict[str, Tensor], gains: Tensor) -> dict[str, Tensor]:
    """``batch`` with the source and target linear radiance multiplied by ``gains [B,3]`` (clamped to [0, 1])."""
    return map_images(batch, lambda x: image_to_model(model_to_image(x) * gains[:, None, None, :]))


COLOR_PERMUTATIONS = torch.tensor([[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]])
"""The 6 orders of the channels (R, G, B); row 0 is the identity."""


def permute_colors(batch: dict[str, Tensor], orders: Tensor) -> dict[str, Tensor]:
    """``batch`` with the source and target channels of pair ``b`` taken in the order ``orders[b] [3]`` (long)."""

    def permuted(model_space: Tensor) -> Tensor:
        index = orders.to(model_space.device)[:, :, None, None].expand(-1, -1, *model_space.shape[-2:])
        return model_space.gather(1, index)

    return map_images(batch, permuted)


def augment_batch(
    batch: dict[str, Tensor], config: RelightAugmentConfig, generator: torch.Generator
) -> dict[str, Tensor]:
    """Randomly mirrored, re-exposed and colour-permuted ``batch``; the draws come from ``generator`` (CPU)."""
    count = batch["target"].shape[0]
    device = batch["target"].device
    chosen = torch.rand(count, generator=generator) < 0.5
    exposure = torch.rand(count, 1, generator=generator) * 2.0 - 1.0
    tint = torch.rand(count, 3, generator=generator) * 2.0 - 1.0
    orders = COLOR_PERMUTATIONS[torch.randint(len(COLOR_PERMUTATIONS), (count,), generator=generator)]
    if config.mirror:
        batch = mirror_batch(batch, to_device(chosen, device))
    if config.exposure > 0.0 or config.tint > 0.0:
        gains = torch.exp2(config.exposure * exposure) * torch.exp(config.tint * tint)
        batch = scale_radiance(batch, to_device(gains.to(batch["target"].dtype), device))
    if config.permute_colors:
        batch = permute_colors(batch, to_device(orders, device))
    return batch
