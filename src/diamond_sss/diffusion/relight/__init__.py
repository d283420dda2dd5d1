"""Relighting diffusion model (supplement Sec. C.3): ControlNet + UNet conditioned on an SH light code."""

from diamond_sss.diffusion.relight.config import RelightModelConfig
from diamond_sss.diffusion.relight.light import light_code
from diamond_sss.diffusion.relight.model import RelightDiffusion

__all__ = ["RelightDiffusion", "RelightModelConfig", "light_code"]
