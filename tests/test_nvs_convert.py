"""Free3D checkpoint converter: complete, shape-exact mapping of the official key names."""

from __future__ import annotations

import pytest
import torch

from diamond_sss.diffusion.nvs.convert import convert_free3d_state_dict, free3d_config, load_free3d_checkpoint
from diamond_sss.diffusion.nvs.model import NVSConfig, NVSModel

# A tiny UNet laid out like Free3D's openaimodel.UNetModel: channel_mult (1, 2, 2), 2 ResBlocks per level,
# spatial transformers (with attn3d) at the first two levels, none at the last; ray conditioning on.
CH, MULT, N_RES, ATTN_LEVELS, HEADS, CTX, IN_CH, OUT_CH = 16, (1, 2, 2), 2, (0, 1), 2, 32, 8, 4
TIME = 4 * CH


def _resblock(prefix: str, ch: int, out: int) -> dict[str, tuple[int, ...]]:
    shapes = {
        f"{prefix}in_layers.0.weight": (ch,),
        f"{prefix}in_layers.0.bias": (ch,),
        f"{prefix}in_layers.2.weight": (out, ch, 3, 3),
        f"{prefix}in_layers.2.bias": (out,),
        f"{prefix}emb_layers.1.weight": (out, TIME),
        f"{prefix}emb_layers.1.bias": (out,),
        f"{prefix}out_layers.0.weight": (out,),
        f"{prefix}out_layers.0.bias": (out,),
        f"{prefix}out_layers.3.weight": (out, out, 3, 3),
        f"{prefix}out_layers.3.bias": (out,),
        f"{prefix}pose_layers.0.weight": (2 * ch, 78, 1, 1),
        f"{prefix}pose_layers.0.bias": (2 * ch,),
    }
    if ch != out:
        shapes[f"{prefix}skip_connection.weight"] = (out, ch, 1, 1)
        shapes[f"{prefix}skip_connection.bias"] = (out,)
    return shapes


def _attention(prefix: str, dim: int, context: int) -> dict[str, tuple[int, ...]]:
    return {
        f"{prefix}to_q.weight": (dim, dim),
        f"{prefix}to_k.weight": (dim, context),
        f"{prefix}to_v.weight": (dim, context),
        f"{prefix}to_out.0.weight": (dim, dim),
        f"{prefix}to_out.0.bias": (dim,),
    }


def _transformer(prefix: str, ch: int) -> dict[str, tuple[int, ...]]:
    block = f"{prefix}transformer_blocks.0."
    shapes = {
        f"{prefix}norm.weight": (ch,),
        f"{prefix}norm.bias": (ch,),
        f"{prefix}proj_in.weight": (ch, ch, 1, 1),
        f"{prefix}proj_in.bias": (ch,),
        f"{prefix}proj_out.weight": (ch, ch, 1, 1),
        f"{prefix}proj_out.bias": (ch,),
        f"{block}ff.net.0.proj.weight": (8 * ch, ch),
        f"{block}ff.net.0.proj.bias": (8 * ch,),
        f"{block}ff.net.2.weight": (ch, 4 * ch),
        f"{block}ff.net.2.bias": (ch,),
    }
    shapes.update(_attention(f"{block}attn1.", ch, ch))
    shapes.update(_attention(f"{block}attn2.", ch, CTX))
    shapes.update(_attention(f"{block}attn3d.", ch, ch))
    for norm in ("norm1", "norm2", "norm3", "norm4"):
        shapes[f"{block}{norm}.weight"] = (ch,)
        shapes[f"{block}{norm}.bias"] = (ch,)
    return shapes


def official_free3d_shapes() -> dict[str, tuple[int, ...]]:
    """Key names and shapes following Free3D's UNetModel construction order."""
    p = "model.diffusion_model."
    shapes = {
        f"{p}time_embed.0.weight": (TIME, CH),
        f"{p}time_embed.0.bias": (TIME,),
        f"{p}time_embed.2.weight": (TIME, TIME),
        f"{p}time_embed.2.bias": (TIME,),
        f"{p}input_blocks.0.0.weight": (CH, IN_CH, 3, 3),
        f"{p}input_blocks.0.0.bias": (CH,),
    }
    chans, ch, index = [CH], CH, 1
    for level, mult in enumerate(MULT):
        for _ in range(N_RES):
            shapes.update(_resblock(f"{p}input_blocks.{index}.0.", ch, mult * CH))
            ch = mult * CH
            if level in ATTN_LEVELS:
                shapes.update(_transformer(f"{p}input_blocks.{index}.1.", ch))
            chans.append(ch)
            index += 1
        if level != len(MULT) - 1:
            shapes[f"{p}input_blocks.{index}.0.op.weight"] = (ch, ch, 3, 3)
            shapes[f"{p}input_blocks.{index}.0.op.bias"] = (ch,)
            chans.append(ch)
            index += 1
    shapes.update(_resblock(f"{p}middle_block.0.", ch, ch))
    shapes.update(_transformer(f"{p}middle_block.1.", ch))
    shapes.update(_resblock(f"{p}middle_block.2.", ch, ch))
    index = 0
    for level, mult in list(enumerate(MULT))[::-1]:
        for i in range(N_RES + 1):
            shapes.update(_resblock(f"{p}output_blocks.{index}.0.", ch + chans.pop(), CH * mult))
            ch = CH * mult
            layer = 1
            if level in ATTN_LEVELS:
                shapes.update(_transformer(f"{p}output_blocks.{index}.1.", ch))
                layer = 2
            if level and i == N_RES:
                shapes[f"{p}output_blocks.{index}.{layer}.conv.weight"] = (ch, ch, 3, 3)
                shapes[f"{p}output_blocks.{index}.{layer}.conv.bias"] = (ch,)
            index += 1
    shapes.update(
        {
            f"{p}out.0.weight": (ch,),
            f"{p}out.0.bias": (ch,),
            f"{p}out.2.weight": (OUT_CH, CH, 3, 3),
            f"{p}out.2.bias": (OUT_CH,),
            "cc_projection.weight": (CTX, CTX),
            "cc_projection.bias": (CTX,),
            "first_stage_model.encoder.conv_in.weight": (8, 3, 3, 3),
            "betas": (1000,),
            "cond_stage_model.model.visual.proj": (16, 8),
        }
    )
    return shapes


def tiny_free3d_config() -> NVSConfig:
    return NVSConfig(
        image_size=16,
        block_out_channels=tuple(CH * m for m in MULT),
        down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
        layers_per_block=N_RES,
        attention_head_dim=HEADS,
        norm_num_groups=8,
        cross_attention_dim=CTX,
        embed_dim=CTX - 4,
        warp_hint=False,
    )


@pytest.fixture
def official_state() -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return {k: torch.randn(shape, generator=g) for k, shape in official_free3d_shapes().items()}


def test_converter_mapping_is_complete_and_shape_exact(official_state):
    model = NVSModel(tiny_free3d_config())
    converted, skipped = convert_free3d_state_dict(official_state, model.config)
    assert sorted(skipped) == [
        "betas",
        "cond_stage_model.model.visual.proj",
        "first_stage_model.encoder.conv_in.weight",
    ]
    ours = model.state_dict()
    expected = {k for k in ours if k.startswith(("unet.", "context_projection."))}
    assert set(converted) == expected  # every official UNet key lands on a distinct key, none is left out
    for key, value in converted.items():
        assert value.shape == ours[key].shape, key
    missing, unexpected = model.load_state_dict(converted, strict=False)
    assert unexpected == []
    assert sorted(missing) == sorted(
        k for k in ours if k.startswith(("reference_encoder.", "null_embedding"))
    )
    state = model.state_dict()
    torch.testing.assert_close(
        state["unet.down_blocks.1.resnets.0.ray_proj.weight"],
        official_state["model.diffusion_model.input_blocks.4.0.pose_layers.0.weight"],
    )
    torch.testing.assert_close(
        state["unet.up_blocks.1.attentions.2.transformer_blocks.0.attn_mv.to_q.weight"],
        official_state["model.diffusion_model.output_blocks.5.1.transformer_blocks.0.attn3d.to_q.weight"],
    )
    torch.testing.assert_close(
        state["unet.up_blocks.1.upsamplers.0.conv.weight"],
        official_state["model.diffusion_model.output_blocks.5.2.conv.weight"],
    )


def test_converter_rejects_unknown_keys_and_reads_files(official_state, tmp_path):
    config = tiny_free3d_config()
    with pytest.raises(KeyError, match="no mapping"):
        convert_free3d_state_dict(
            {**official_state, "model.diffusion_model.extra.weight": torch.zeros(1)}, config
        )
    torch.save({"state_dict": official_state}, tmp_path / "free3d.ckpt")
    converted, _ = load_free3d_checkpoint(tmp_path / "free3d.ckpt", config)
    assert len(converted) == len(official_state) - 3
    with pytest.raises(FileNotFoundError):
        load_free3d_checkpoint(tmp_path / "missing.ckpt", config)


def test_official_architecture_config_matches_free3d():
    config = free3d_config()
    assert config.model_size == 32 and config.latent_scale == 0.18215
    assert config.block_out_channels == (320, 640, 1280, 1280) and config.cross_attention_dim == 768
