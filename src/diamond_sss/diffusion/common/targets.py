"""v-parameterisation (Salimans & Ho 2022): ``x_t = a x_0 + s eps``, ``v = a eps - s x_0``, ``x_0 = a x_t - s v``.

``a = sqrt(alpha_bar_t)``, ``s = sqrt(1 - alpha_bar_t)``.
"""

from __future__ import annotations

from torch import Tensor


def _coefficients(alphas_cumprod: Tensor, timesteps: Tensor, ndim: int) -> tuple[Tensor, Tensor]:
    alpha_bar = alphas_cumprod.to(timesteps.device)[timesteps].float()
    shape = (-1,) + (1,) * (ndim - 1)
    return alpha_bar.sqrt().reshape(shape), (1.0 - alpha_bar).sqrt().reshape(shape)


def v_target(clean: Tensor, noise: Tensor, alphas_cumprod: Tensor, timesteps: Tensor) -> Tensor:
    """Velocity target ``v = a eps - s x_0``. ``clean``, ``noise`` ``[B,...]``, ``timesteps [B]`` (long)."""
    a, s = _coefficients(alphas_cumprod, timesteps, clean.ndim)
    return a * noise - s * clean


def predicted_clean(noisy: Tensor, v: Tensor, alphas_cumprod: Tensor, timesteps: Tensor) -> Tensor:
    """Clean sample implied by a velocity prediction: ``x_0 = a x_t - s v``."""
    a, s = _coefficients(alphas_cumprod, timesteps, noisy.ndim)
    return a * noisy - s * v
