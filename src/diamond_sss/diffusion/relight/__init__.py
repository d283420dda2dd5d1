"""Relighting diffusion model (supplement Sec. C.3): ControlNet + UNet conditioned on an SH light code
(import the modules: ``config`` imports without torch)."""
