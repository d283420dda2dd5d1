"""Exponential moving average of a module's parameters (the weights that get shipped)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from diamond_sss.errors import DamagedFileError
from diamond_sss.utils.io import atomic_save_safetensors, load_safetensors

if TYPE_CHECKING:
    from accelerate import Accelerator

EMA_FILE = "ema.safetensors"
"""The EMA's state in a fine-tune's checkpoint folder (``step_<N>``), beside what ``accelerator.save_state`` writes."""


class EMA:
    """Shadow copy ``s <- d s + (1 - d) p`` of every floating-point parameter and buffer of ``module``.

    The decay warms up as ``d_k = min(decay, (1 + k) / (10 + k))`` so early averages are not dominated
    by the random initialisation. ``state_dict`` / ``load_state_dict`` make it resumable.
    """

    def __init__(self, module: nn.Module, decay: float = 0.999) -> None:
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"EMA decay must be in [0, 1), got {decay}")
        self.decay = decay
        self.num_updates = 0
        self.shadow = {k: v.detach().clone() for k, v in _float_state(module).items()}

    def current_decay(self) -> float:
        """Decay used by the next update."""
        return min(self.decay, (1.0 + self.num_updates) / (10.0 + self.num_updates))

    @torch.no_grad()
    def update(self, module: nn.Module) -> None:
        """Blend the module's current weights into the shadow."""
        decay = self.current_decay()
        state = _float_state(module)
        shadows = list(self.shadow.values())
        values = [state[key].detach().to(shadow.device) for key, shadow in self.shadow.items()]
        torch._foreach_lerp_(shadows, values, 1.0 - decay)  # one fused kernel per dtype on CUDA, not one per tensor
        self.num_updates += 1

    @torch.no_grad()
    def copy_to(self, module: nn.Module) -> None:
        """Write the averaged weights into ``module``."""
        state = _float_state(module)
        for key, value in self.shadow.items():
            state[key].copy_(value)

    @contextmanager
    def averaged(self, module: nn.Module) -> Iterator[nn.Module]:
        """Temporarily swap the averaged weights into ``module`` (restored on exit)."""
        backup = {k: v.detach().clone() for k, v in _float_state(module).items()}
        self.copy_to(module)
        try:
            yield module
        finally:
            with torch.no_grad():
                state = _float_state(module)
                for key, value in backup.items():
                    state[key].copy_(value)

    def state_dict(self) -> dict[str, Tensor]:
        """Shadow tensors plus the update counter (as a tensor, safetensors-friendly)."""
        return {
            **{f"shadow.{k}": v for k, v in self.shadow.items()},
            "num_updates": torch.tensor(self.num_updates, dtype=torch.int64),
        }

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        missing = [k for k in self.shadow if f"shadow.{k}" not in state]
        if missing or "num_updates" not in state:
            raise KeyError(f"EMA state is missing {missing[:3] or ['num_updates']}")
        for key in self.shadow:
            self.shadow[key].copy_(state[f"shadow.{key}"])
        self.num_updates = int(state["num_updates"])


def save_ema_with_checkpoints(accelerator: Accelerator, ema: EMA) -> None:
    """Make every ``accelerator.save_state`` also write ``ema``'s state as :data:`EMA_FILE` (safetensors, atomically)
    into the folder it saves (from the main process: every process runs the hook), so the checkpoint holds it when
    that folder is published. accelerate's ``register_for_checkpointing`` would store it as a pickle and load it
    back with ``weights_only=False``."""

    def save(models: list, weights: list, output_dir: str) -> None:
        if accelerator.is_main_process:
            atomic_save_safetensors(Path(output_dir) / EMA_FILE, ema.state_dict())

    accelerator.register_save_state_pre_hook(save)


def load_checkpoint_ema(ema: EMA, folder: str | os.PathLike) -> None:
    """Restore ``ema`` from the :data:`EMA_FILE` of checkpoint ``folder``. A checkpoint without it (damaged, or
    written before the EMA was stored so) or with another model's EMA is a :class:`DamagedFileError` naming it."""
    path = Path(folder) / EMA_FILE
    if not path.is_file():
        raise DamagedFileError(f"{path}: missing: checkpoint {folder} holds no EMA weights (damaged, or written by "
                               "an older version); fine-tune into another --out")
    try:
        ema.load_state_dict(load_safetensors(path))
    except (KeyError, RuntimeError) as exc:
        raise DamagedFileError(f"{path}: not the EMA of the model being fine-tuned ({exc})") from exc


def _float_state(module: nn.Module) -> dict[str, Tensor]:
    return {k: v for k, v in module.state_dict(keep_vars=True).items() if v.is_floating_point()}
