"""Learning-rate schedules."""

from __future__ import annotations

import math


def exponential_lr(step: int, lr_init: float, lr_final: float, max_steps: int, delay_steps: int = 0,
                   delay_mult: float = 1.0) -> float:
    """3DGS / Plenoxels position schedule: log-linear from ``lr_init`` to ``lr_final`` over ``max_steps``.

    ``lr(t) = delay(t) exp((1 - u) log lr_init + u log lr_final)``, ``u = clip(t / max_steps, 0, 1)``;
    with ``delay_steps > 0``, ``delay(t) = m + (1 - m) sin(pi/2 clip(t / delay_steps, 0, 1))``,
    ``m = delay_mult``, else 1.
    """
    if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
        return 0.0
    if delay_steps > 0:
        delay = delay_mult + (1.0 - delay_mult) * math.sin(0.5 * math.pi * min(max(step / delay_steps, 0.0), 1.0))
    else:
        delay = 1.0
    u = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return delay * math.exp((1.0 - u) * math.log(lr_init) + u * math.log(lr_final))


def step_decay(step: int, decay_step: int, factor: float) -> float:
    """Multiplier ``factor`` from ``decay_step`` on, 1 before (supplement A.1: x0.1 after 50k steps)."""
    return factor if step >= decay_step else 1.0


def linear_warmup(step: int, warmup_steps: int) -> float:
    """Multiplier ``min(1, (t + 1) / warmup_steps)`` of a learning rate warmed up over ``warmup_steps`` (1 if 0)."""
    return 1.0 if warmup_steps <= 0 else min(1.0, (step + 1) / warmup_steps)
