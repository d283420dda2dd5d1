"""The noise schedulers of both diffusion models (diffusers' DDPM for training, DDIM for sampling).

diffusers is imported when a scheduler is made, so that the model configs holding a :class:`SchedulerConfig`
import without torch (the command line derives its options from them)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from diffusers import DDIMScheduler, DDPMScheduler


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
    from diffusers import DDPMScheduler

    return DDPMScheduler(**config.kwargs(), clip_sample=False)


def make_ddim_scheduler(config: SchedulerConfig, clip_range: float | None = None) -> DDIMScheduler:
    """Deterministic sampling scheduler (DDIM, ``eta = 0``) on the same schedule.

    ``trailing`` timestep spacing, so the first step is at ``t = T - 1`` (pure noise) whatever the step count,
    and a last step that lands on the clean prediction. With ``clip_range`` the clean estimate is clipped to
    ``[-clip_range, clip_range]`` at every step.
    """
    from diffusers import DDIMScheduler

    return DDIMScheduler(
        **config.kwargs(),
        clip_sample=clip_range is not None,
        clip_sample_range=1.0 if clip_range is None else clip_range,
        set_alpha_to_one=True,
        timestep_spacing="trailing",
    )
