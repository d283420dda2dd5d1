"""Free3D layers grafted onto a diffusers ``UNet2DConditionModel``.

* :class:`RayConditionedResnetBlock`: a ``ResnetBlock2D`` whose first normalisation is modulated by the
  harmonic-embedded Plucker rays, ``h = act(norm1(x)) * (1 + s) + b`` with ``(s, b) = conv1x1(rays)``
  (zero-initialised, so a fresh block computes exactly what the plain block computes).
* :class:`MultiViewTransformerBlock`: a ``BasicTransformerBlock`` with an extra attention across the views
  of one object at each pixel, between cross-attention and the feed-forward (zero-initialised output).

Both keep the wrapped block's parameter names, so plain diffusers weights load unchanged, and both read the
per-call conditioning (ray embedding, views per object) from a shared :class:`ConditioningSlot` that the
UNet wrapper fills for the duration of one forward pass. Gradient checkpointing is done here, with the
conditioning passed explicitly, so that recomputation in the backward pass does not depend on the slot.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from diffusers.models.attention import BasicTransformerBlock
from diffusers.models.attention_processor import Attention
from diffusers.models.resnet import ResnetBlock2D
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from diamond_sss.diffusion.nvs.rays import RAY_EMBEDDING_CHANNELS


@dataclass
class ConditioningSlot:
    """Per-forward conditioning of the grafted layers: ``rays [B,78,h,w]`` or None, views per object."""

    rays: Tensor | None = None
    num_views: int = 1


class RayConditionedResnetBlock(nn.Module):
    """``ResnetBlock2D`` with ray-conditioning normalisation (Free3D ``pose_layers``)."""

    def __init__(
        self, block: ResnetBlock2D, slot: ConditioningSlot, ray_channels: int = RAY_EMBEDDING_CHANNELS
    ):
        super().__init__()
        if (
            block.time_embedding_norm != "default"
            or block.upsample is not None
            or block.downsample is not None
        ):
            raise ValueError(
                "ray conditioning supports plain ResnetBlock2D blocks (default norm, no up/down)"
            )
        self.norm1, self.conv1, self.norm2, self.conv2 = block.norm1, block.conv1, block.norm2, block.conv2
        self.time_emb_proj, self.conv_shortcut = block.time_emb_proj, block.conv_shortcut
        self.dropout, self.nonlinearity = block.dropout, block.nonlinearity
        self.skip_time_act = block.skip_time_act
        self.output_scale_factor = block.output_scale_factor
        self.ray_proj = nn.Conv2d(ray_channels, 2 * block.in_channels, kernel_size=1)
        nn.init.zeros_(self.ray_proj.weight)
        nn.init.zeros_(self.ray_proj.bias)
        self.slot = [slot]  # a list keeps the slot out of the module tree and the state dict
        self.gradient_checkpointing = False

    def forward(self, input_tensor: Tensor, temb: Tensor | None, *args, **kwargs) -> Tensor:
        rays = self.slot[0].rays
        if self.gradient_checkpointing and torch.is_grad_enabled():
            return checkpoint(self._forward, input_tensor, temb, rays, use_reentrant=False)
        return self._forward(input_tensor, temb, rays)

    def _forward(self, x: Tensor, temb: Tensor | None, rays: Tensor | None) -> Tensor:
        h = self.nonlinearity(self.norm1(x))
        if rays is not None:
            rays = F.interpolate(rays.to(h.dtype), size=h.shape[-2:], mode="bilinear", align_corners=True)
            scale, shift = self.ray_proj(rays).chunk(2, dim=1)
            h = h * (1 + scale) + shift
        h = self.conv1(h)
        if self.time_emb_proj is not None and temb is not None:
            if not self.skip_time_act:
                temb = self.nonlinearity(temb)
            h = h + self.time_emb_proj(temb)[:, :, None, None]
        h = self.conv2(self.dropout(self.nonlinearity(self.norm2(h))))
        if self.conv_shortcut is not None:
            x = self.conv_shortcut(x.contiguous())
        return (x + h) / self.output_scale_factor


def multi_view_attention(attention: Attention, norm: nn.LayerNorm, x: Tensor, num_views: int) -> Tensor:
    """Residual attention across the ``num_views`` views of one object at each token.

    ``x [B*V, T, C]`` with the views of an object contiguous in the batch -> same shape.
    """
    bv, tokens, channels = x.shape
    if bv % num_views:
        raise ValueError(f"batch {bv} is not a multiple of the views per object ({num_views})")
    seq = x.reshape(bv // num_views, num_views, tokens, channels).transpose(1, 2)
    seq = seq.reshape(-1, num_views, channels)
    out = attention(norm(seq))
    out = (
        out.reshape(bv // num_views, tokens, num_views, channels)
        .transpose(1, 2)
        .reshape(bv, tokens, channels)
    )
    return x + out


class MultiViewTransformerBlock(nn.Module):
    """``BasicTransformerBlock`` (layer norm, self- and cross-attention) plus multi-view attention."""

    def __init__(self, block: BasicTransformerBlock, slot: ConditioningSlot):
        super().__init__()
        if block.norm_type != "layer_norm" or block.attn2 is None or block.pos_embed is not None:
            raise ValueError(
                "multi-view attention supports layer-norm transformer blocks with cross-attention"
            )
        self.norm1, self.attn1, self.norm2, self.attn2 = block.norm1, block.attn1, block.norm2, block.attn2
        self.norm3, self.ff = block.norm3, block.ff
        dim = block.norm1.normalized_shape[0]
        heads = block.attn1.heads
        self.norm_mv = nn.LayerNorm(dim)
        self.attn_mv = Attention(query_dim=dim, heads=heads, dim_head=dim // heads, bias=False)
        nn.init.zeros_(self.attn_mv.to_out[0].weight)
        nn.init.zeros_(self.attn_mv.to_out[0].bias)
        self.slot = [slot]
        self.gradient_checkpointing = False

    def forward(
        self,
        hidden_states: Tensor,
        attention_mask: Tensor | None = None,
        encoder_hidden_states: Tensor | None = None,
        *args,
        **kwargs,
    ) -> Tensor:
        num_views = self.slot[0].num_views
        if self.gradient_checkpointing and torch.is_grad_enabled():
            return checkpoint(
                self._forward, hidden_states, encoder_hidden_states, num_views, use_reentrant=False
            )
        return self._forward(hidden_states, encoder_hidden_states, num_views)

    def _forward(self, x: Tensor, context: Tensor | None, num_views: int) -> Tensor:
        x = self.attn1(self.norm1(x)) + x
        x = self.attn2(self.norm2(x), encoder_hidden_states=context) + x
        if num_views > 1:
            x = multi_view_attention(self.attn_mv, self.norm_mv, x, num_views)
        return self.ff(self.norm3(x)) + x


def graft_free3d_layers(unet: nn.Module, slot: ConditioningSlot) -> None:
    """Replace, in place, every ResNet block and transformer block of ``unet`` by its Free3D version."""
    for name, module in list(unet.named_modules()):
        for child_name, child in list(module.named_children()):
            if isinstance(child, ResnetBlock2D):
                setattr(module, child_name, RayConditionedResnetBlock(child, slot))
            elif isinstance(child, BasicTransformerBlock):
                setattr(module, child_name, MultiViewTransformerBlock(child, slot))


def set_layer_checkpointing(unet: nn.Module, enabled: bool) -> None:
    """Turn gradient checkpointing of the grafted blocks on or off."""
    for module in unet.modules():
        if isinstance(module, (RayConditionedResnetBlock, MultiViewTransformerBlock)):
            module.gradient_checkpointing = enabled
