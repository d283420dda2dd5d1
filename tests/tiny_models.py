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
