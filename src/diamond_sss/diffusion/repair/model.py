"""The repair network: a diffusers ``UNet2DModel`` (no attention) run once at a fixed timestep, whose output corrects
the render it is given (one step from the render, as Difix3D+ repairs renders, instead of many from noise).

    y_rgb = clamp(srgb(R) + f(x)_rgb, 0, 1),   y_alpha = clamp(alpha(R) + f(x)_alpha, 0, 1)

with ``x`` the input of :mod:`.inputs` (its first 4 channels are ``srgb(R)`` and ``alpha(R)``). The last layer starts
at zero, so an untrained model returns the render. Images whose sides are not multiples of ``2^(levels-1)`` are
padded at the bottom and right (replicated) and cropped back.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path

import torch
import torch.nn.functional as F
from diffusers import UNet2DModel
from torch import Tensor, nn

from diamond_sss.diffusion.common.model_io import load_weights, read_model_config, save_model
from diamond_sss.diffusion.repair.config import INPUT_CHANNELS, OUTPUT_CHANNELS, RepairModelConfig

KIND = "repair"
TIMESTEP = 0
"""The one timestep the network runs at."""


class RepairModel(nn.Module):
    """The repair UNet and its configuration; :meth:`save` / :meth:`load` use the diffusion models' folder layout
    (:mod:`~diamond_sss.diffusion.common.model_io`)."""

    def __init__(self, config: RepairModelConfig | None = None) -> None:
        super().__init__()
        self.config = config or RepairModelConfig()
        levels = len(self.config.block_out_channels)
        self.unet = UNet2DModel(in_channels=INPUT_CHANNELS, out_channels=OUTPUT_CHANNELS,
                                block_out_channels=self.config.block_out_channels,
                                layers_per_block=self.config.layers_per_block,
                                down_block_types=("DownBlock2D",) * levels, up_block_types=("UpBlock2D",) * levels,
                                norm_num_groups=self.config.norm_num_groups)
        nn.init.zeros_(self.unet.conv_out.weight)
        nn.init.zeros_(self.unet.conv_out.bias)

    @property
    def multiple(self) -> int:
        """Image sides the UNet takes: multiples of this."""
        return 2 ** (len(self.config.block_out_channels) - 1)

    def forward(self, inputs: Tensor) -> Tensor:
        """``inputs [B, 23, H, W]`` -> the repaired premultiplied sRGB and alpha ``[B, 4, H, W]`` in [0, 1]."""
        height, width = inputs.shape[-2:]
        pad_h, pad_w = -height % self.multiple, -width % self.multiple
        padded = F.pad(inputs, (0, pad_w, 0, pad_h), mode="replicate") if pad_h or pad_w else inputs
        timestep = torch.full((inputs.shape[0],), TIMESTEP, device=inputs.device)
        correction = self.unet(padded, timestep).sample[..., :height, :width]
        return (inputs[:, :OUTPUT_CHANNELS] + correction).clamp(0, 1)

    def save(self, folder: str | os.PathLike) -> Path:
        """Write ``config.json`` and ``model.safetensors`` into ``folder``."""
        config = asdict(self.config) | {"block_out_channels": list(self.config.block_out_channels)}
        return save_model(folder, KIND, config, self.state_dict())

    @classmethod
    def load(cls, folder: str | os.PathLike, device: str | torch.device = "cpu") -> RepairModel:
        """The model saved in ``folder``, in eval mode on ``device``."""
        config, _ = read_model_config(folder, KIND, legacy=lambda raw: {"config": raw["config"]})
        model = cls(RepairModelConfig(**{**config, "block_out_channels": tuple(config["block_out_channels"])}))
        load_weights(model, folder)
        return model.to(device).eval()
