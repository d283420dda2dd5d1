"""What the diffusion pipelines share: the deterministic DDIM loop (eta = 0) and their one output type."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from diffusers import DDIMScheduler
from torch import Tensor


@dataclass
class PipelineOutput:
    """Images made by a diffusion pipeline, float32 on the CPU.

    ``rgb [N,H,W,3]`` linear premultiplied colour in ``[0, 1]``; ``alpha [N,H,W,1]`` its coverage, or ``None``
    where the pipeline makes none (relighting keeps the source image's mask).
    """

    rgb: Tensor
    alpha: Tensor | None = None


DenoiseFn = Callable[[Tensor, Tensor], Tensor]

@torch.no_grad()
def ddim_sample(
    denoise: DenoiseFn,
    shape: tuple[int, ...],
    scheduler: DDIMScheduler,
    num_steps: int,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
    noise: Tensor | None = None,
) -> Tensor:
    """Run ``num_steps`` DDIM steps (eta = 0) from Gaussian noise of ``shape``.

    ``denoise(x_t [B,...], t [B]) -> model output`` in the scheduler's parameterisation. The initial noise
    is ``noise`` when given, else drawn on the CPU from ``generator`` so a seed gives the same sample on
    every device.
    """
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    if noise is not None and tuple(noise.shape) != tuple(shape):
        raise ValueError(f"noise has shape {tuple(noise.shape)}, expected {tuple(shape)}")
    scheduler.set_timesteps(num_steps, device=device)
    if noise is None:
        noise = torch.randn(shape, generator=generator, dtype=torch.float32)
    sample = noise.to(device=device, dtype=dtype)
    sample = sample * scheduler.init_noise_sigma
    for t in scheduler.timesteps:
        timesteps = torch.full((shape[0],), int(t), device=device, dtype=torch.long)
        output = denoise(sample, timesteps)
        sample = scheduler.step(output, t, sample, eta=0.0).prev_sample
    return sample
