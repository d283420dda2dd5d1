"""Configurations of tiny randomly initialised diffusion models shared by the tests (no weights, no download)."""

from __future__ import annotations

TINY_NVS = {
    "image_size": 16,
    "block_out_channels": (16, 32),
    "down_block_types": ("DownBlock2D", "CrossAttnDownBlock2D"),
    "up_block_types": ("CrossAttnUpBlock2D", "UpBlock2D"),
    "attention_head_dim": 8,
    "norm_num_groups": 8,
    "cross_attention_dim": 32,
    "embed_dim": 16,
    "encoder_channels": (8,),
}
"""``NVSConfig`` keyword arguments of a 16-pixel novel-view model."""

TINY_RELIGHT = {
    "resolution": 16,
    "block_out_channels": (8, 16),
    "norm_num_groups": 4,
    "cross_attention_dim": 8,
    "attention_head_dim": 4,
    "light_tokens": 2,
}
"""``RelightModelConfig`` keyword arguments of a 16-pixel relighting model."""


def tiny_sd_unet(in_channels: int, cross_attention_dim: int):
    """A two-level ``UNet2DConditionModel`` of Stable Diffusion's layout (8-pixel latents, 4 output channels)."""
    from diffusers import UNet2DConditionModel

    return UNet2DConditionModel(
        sample_size=8,
        in_channels=in_channels,
        out_channels=4,
        block_out_channels=(8, 16),
        down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
        up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"),
        layers_per_block=1,
        cross_attention_dim=cross_attention_dim,
        norm_num_groups=4,
        attention_head_dim=4,
    )


def tiny_vae(levels: int = 2):
    """An ``AutoencoderKL`` with 4 latent channels and ``levels`` resolution levels (downsampling 2^(levels-1))."""
    from diffusers import AutoencoderKL

    return AutoencoderKL(
        in_channels=3,
        out_channels=3,
        latent_channels=4,
        block_out_channels=(8,) * levels,
        down_block_types=("DownEncoderBlock2D",) * levels,
        up_block_types=("UpDecoderBlock2D",) * levels,
        norm_num_groups=4,
        layers_per_block=1,
    )
