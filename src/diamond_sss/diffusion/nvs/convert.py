"""Load the official Free3D checkpoint (LDM / ``openaimodel`` key names) into :class:`NVSModel`.

The official UNet is ``model.diffusion_model.*`` (``input_blocks / middle_block / output_blocks``, ResBlocks
with ``pose_layers`` for ray conditioning, transformer blocks with ``attn3d`` / ``norm4`` for multi-view
attention) and the context projection is ``cc_projection``. The VAE (``first_stage_model.*``) and the CLIP
image encoder (``cond_stage_model.*``) are not part of :class:`NVSModel`'s weights: they are reported as
skipped and must be provided as local diffusers / transformers folders.
"""

from __future__ import annotations

import re
from pathlib import Path

import torch
from torch import Tensor

from diamond_sss.diffusion.nvs.model import NVSConfig

UNET_PREFIX = "model.diffusion_model."
SKIPPED_PREFIXES = ("first_stage_model.", "cond_stage_model.", "model_ema.")
SKIPPED_BUFFERS = (
    "betas",
    "alphas_cumprod",
    "alphas_cumprod_prev",
    "sqrt_alphas_cumprod",
    "sqrt_one_minus_alphas_cumprod",
    "log_one_minus_alphas_cumprod",
    "sqrt_recip_alphas_cumprod",
    "sqrt_recipm1_alphas_cumprod",
    "posterior_variance",
    "posterior_log_variance_clipped",
    "posterior_mean_coef1",
    "posterior_mean_coef2",
    "logvar",
    "scale_factor",
)

RESBLOCK_NAMES = {
    "in_layers.0": "norm1",
    "in_layers.2": "conv1",
    "emb_layers.1": "time_emb_proj",
    "out_layers.0": "norm2",
    "out_layers.3": "conv2",
    "skip_connection": "conv_shortcut",
    "pose_layers.0": "ray_proj",
}
TRANSFORMER_NAMES = {"attn3d": "attn_mv", "norm4": "norm_mv"}
TOP_LEVEL_NAMES = {
    "time_embed.0": "time_embedding.linear_1",
    "time_embed.2": "time_embedding.linear_2",
    "input_blocks.0.0": "conv_in",
    "out.0": "conv_norm_out",
    "out.2": "conv_out",
}


def free3d_config(image_size: int = 256, vae_path: str | None = None) -> NVSConfig:
    """Architecture of the official Free3D UNet (Stable Diffusion 1.x layout, 8 input channels)."""
    return NVSConfig(
        space="latent",
        image_size=image_size,
        vae_path=vae_path,
        block_out_channels=(320, 640, 1280, 1280),
        down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
        up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3,
        layers_per_block=2,
        attention_head_dim=8,
        norm_num_groups=32,
        cross_attention_dim=768,
        embed_dim=768,
        warp_hint=False,
    )


def _rename(rest: str, table: dict[str, str]) -> str:
    for old, new in table.items():
        if rest == old or rest.startswith(old + "."):
            return new + rest[len(old) :]
    return rest


def _resnet(rest: str) -> str:
    renamed = _rename(rest, RESBLOCK_NAMES)
    if renamed == rest:
        raise KeyError(rest)
    return renamed


def _transformer(rest: str) -> str:
    match = re.match(r"transformer_blocks\.(\d+)\.(.+)", rest)
    if match:
        return f"transformer_blocks.{match[1]}.{_rename(match[2], TRANSFORMER_NAMES)}"
    if rest.split(".")[0] in ("norm", "proj_in", "proj_out"):
        return rest
    raise KeyError(rest)


def unet_key(key: str, config: NVSConfig) -> str:
    """diffusers name (inside ``NVSModel.unet``) of an official UNet key (no ``model.diffusion_model.``)."""
    for old, new in TOP_LEVEL_NAMES.items():
        if key.startswith(old + "."):
            return new + key[len(old) :]
    n = config.layers_per_block
    down_attention = ["CrossAttn" in t for t in config.down_block_types]
    up_attention = ["CrossAttn" in t for t in config.up_block_types]
    middle = re.match(r"middle_block\.(\d+)\.(.+)", key)
    if middle:
        layer, rest = int(middle[1]), middle[2]
        if layer == 1:
            return f"mid_block.attentions.0.{_transformer(rest)}"
        if layer in (0, 2):
            return f"mid_block.resnets.{layer // 2}.{_resnet(rest)}"
        raise KeyError(key)
    match = re.match(r"(input_blocks|output_blocks)\.(\d+)\.(\d+)\.(.+)", key)
    if match is None:
        raise KeyError(key)
    part, i, layer, rest = match[1], int(match[2]), int(match[3]), match[4]
    if part == "input_blocks":
        level, j = divmod(i - 1, n + 1)
        if j == n:
            if layer != 0 or not rest.startswith("op."):
                raise KeyError(key)
            return f"down_blocks.{level}.downsamplers.0.conv.{rest[3:]}"
        if layer == 0:
            return f"down_blocks.{level}.resnets.{j}.{_resnet(rest)}"
        if layer == 1 and down_attention[level]:
            return f"down_blocks.{level}.attentions.{j}.{_transformer(rest)}"
        raise KeyError(key)
    up, j = divmod(i, n + 1)
    if layer == 0:
        return f"up_blocks.{up}.resnets.{j}.{_resnet(rest)}"
    if layer == 1 and up_attention[up]:
        return f"up_blocks.{up}.attentions.{j}.{_transformer(rest)}"
    if layer == (2 if up_attention[up] else 1) and j == n and rest.startswith("conv."):
        return f"up_blocks.{up}.upsamplers.0.{rest}"
    raise KeyError(key)


def convert_free3d_state_dict(
    official: dict[str, Tensor], config: NVSConfig
) -> tuple[dict[str, Tensor], list[str]]:
    """Rename an official Free3D state dict to :class:`NVSModel` keys.

    Returns ``(converted, skipped)``; ``skipped`` lists the VAE / CLIP / schedule keys left out. Raises
    ``KeyError`` naming every key that has no mapping (so a silent partial load cannot happen).
    """
    converted: dict[str, Tensor] = {}
    skipped: list[str] = []
    unknown: list[str] = []
    for key, value in official.items():
        if key.startswith(SKIPPED_PREFIXES) or key in SKIPPED_BUFFERS:
            skipped.append(key)
        elif key.startswith("cc_projection."):
            converted["context_projection." + key[len("cc_projection.") :]] = value
        elif key.startswith(UNET_PREFIX):
            try:
                converted["unet." + unet_key(key[len(UNET_PREFIX) :], config)] = value
            except KeyError:
                unknown.append(key)
        else:
            unknown.append(key)
    if unknown:
        raise KeyError(f"{len(unknown)} Free3D keys have no mapping, e.g. {unknown[:5]}")
    return converted, skipped


def load_free3d_checkpoint(path: str | Path, config: NVSConfig) -> tuple[dict[str, Tensor], list[str]]:
    """Read an official ``.ckpt`` (``{"state_dict": ...}``) or ``.safetensors`` file and convert it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Free3D checkpoint {path} not found")
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        state = load_file(str(path))
    else:
        state = torch.load(path, map_location="cpu", weights_only=True)
        state = state.get("state_dict", state)
    return convert_free3d_state_dict(state, config)
