"""Noise schedules and the deterministic DDIM sampling loop (eta = 0), on diffusers' schedulers."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from diffusers import DDIMScheduler, DDPMScheduler
from torch import Tensor


@dataclass(frozen=True)
class SchedulerConfig:
    """Training noise schedule: ``num_train_timesteps`` steps of betas from ``beta_start`` to ``beta_end``."""

    num_train_timesteps: int = 1000
    beta_start: float = 0.00085
    beta_end: float = 0.012
    beta_schedule: str = "scaled_linear"
    prediction_type: str = "v_prediction"
    rescale_betas_zero_snr: bool = True

    def kwargs(self) -> dict:
        return {
            "num_train_timesteps": self.num_train_timesteps,
            "beta_start": self.beta_start,
            "beta_end": self.beta_end,
            "beta_schedule": self.beta_schedule,
            "prediction_type": self.prediction_type,
            "rescale_betas_zero_snr": self.rescale_betas_zero_snr,
        }


def make_ddpm_scheduler(config: SchedulerConfig) -> DDPMScheduler:
    """Training scheduler (``add_noise`` and ``alphas_cumprod``)."""
    return DDPMScheduler(**config.kwargs(), clip_sample=False)


def make_ddim_scheduler(config: SchedulerConfig) -> DDIMScheduler:
    """Sampling scheduler: ``trailing`` spacing (the first step starts at pure noise, zero terminal SNR) and a
    last step that lands on the clean prediction."""
    return DDIMScheduler(
        **config.kwargs(), clip_sample=False, set_alpha_to_one=True, timestep_spacing="trailing"
    )


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
