"""Free3D-style novel-view diffusion (supplement Sec. C.2): ray-conditioned multi-view UNet on diffusers
(import the modules: ``config`` imports without torch)."""
