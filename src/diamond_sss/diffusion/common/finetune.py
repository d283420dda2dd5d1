"""The loop shape both diffusion fine-tunes (novel views, relighting) share: one run-folder layout, one resume check,
one optimiser step with the same gradient clipping, one log record and one checkpoint cadence.

A fine-tune's folder ``out``::

    finetune_config.json   its settings (:data:`SETTINGS`); a resume must give the same but for the resumable ones
    train_log.jsonl        one JSON record per logged step (:data:`LOG`)
    checkpoints/step_<N>   accelerate's state, ``ema.safetensors`` and ``extra.json`` (:data:`CHECKPOINTS`)
    model/                 the EMA weights, written when the loop ends (:data:`MODEL`)

Relighting runs before 2026-12-04 named the settings ``train_config.json`` and the log ``log.jsonl``
(:data:`LEGACY_NAMES`): they are read under those names, and renamed when such a run is resumed.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Collection, Mapping
from pathlib import Path
from typing import Any, Protocol

import torch
from accelerate import Accelerator
from torch import Tensor, nn

from diamond_sss.diffusion.common.checkpoints import (
    latest_accelerate_checkpoint,
    load_accelerate_checkpoint,
    save_accelerate_checkpoint,
)
from diamond_sss.diffusion.common.ema import EMA, load_checkpoint_ema
from diamond_sss.diffusion.common.runtime import Deadline, check_resumed_settings
from diamond_sss.utils.io import atomic_write_json

SETTINGS = "finetune_config.json"
LOG = "train_log.jsonl"
CHECKPOINTS = "checkpoints"
MODEL = "model"
LEGACY_NAMES = {SETTINGS: "train_config.json", LOG: "log.jsonl"}
"""Current file name -> the name older relighting runs wrote."""


class LoopSettings(Protocol):
    """The fields of a fine-tuning config that the loop reads (``FinetuneConfig``, ``RelightTrainConfig``)."""

    steps: int
    log_every: int
    checkpoint_every: int
    keep_checkpoints: int
    max_grad_norm: float | None
    time_limit_s: float | None


def check_loop_settings(config: LoopSettings) -> None:
    """Refuse loop settings no run can use, naming each field and what it must be."""
    bad = [f"{name} must be >= {least}, got {getattr(config, name)!r}"
           for name, least in (("steps", 0), ("log_every", 1), ("checkpoint_every", 1), ("keep_checkpoints", 0))
           if not getattr(config, name) >= least]
    if config.max_grad_norm is not None and not config.max_grad_norm > 0:
        bad.append(f"max_grad_norm must be > 0 or None (not clipped), got {config.max_grad_norm!r}")
    if bad:
        raise ValueError(f"{type(config).__name__}: {'; '.join(bad)}")


def run_file(out: Path, name: str) -> Path:
    """``out/name``, or the file's older name (:data:`LEGACY_NAMES`) when only that exists."""
    legacy = LEGACY_NAMES.get(name)
    if legacy is not None and not (out / name).exists() and (out / legacy).exists():
        return out / legacy
    return out / name


def open_run(out: Path, settings: dict, may_change: Collection[str], implied: Mapping[str, Any], resume: bool,
             log: Callable[[str], None]) -> Path | None:
    """Prepare ``out`` for a fine-tune with ``settings`` (JSON) and return the checkpoint to resume (``None``: start
    at step 0).

    With ``resume`` and a complete checkpoint under ``out/checkpoints``, the recorded settings must equal
    ``settings`` but for the ``may_change`` keys (``implied``: the values a record written before a key existed
    stands for); a refusal leaves ``out`` as it was. Then files under :data:`LEGACY_NAMES` are renamed to the
    current names (saying so) and ``settings`` is written as :data:`SETTINGS`.
    """
    latest = latest_accelerate_checkpoint(out / CHECKPOINTS) if resume else None
    if latest is not None:
        check_resumed_settings(run_file(out, SETTINGS), settings, may_change, implied)
    out.mkdir(parents=True, exist_ok=True)  # after what can be refused: a refused run leaves no folder behind
    for name, legacy in LEGACY_NAMES.items():
        if (out / legacy).exists() and not (out / name).exists():
            os.replace(out / legacy, out / name)
            log(f"{out / legacy} renamed {name} (the fine-tunes' common name)")
    atomic_write_json(out / SETTINGS, settings)
    return latest


def resume_from(accelerator: Accelerator, ema: EMA, folder: Path | None, log: Callable[[str], None]) -> int:
    """Restore the model, optimiser, schedule, RNG states and ``ema`` from checkpoint ``folder``; its step (0 without
    one)."""
    if folder is None:
        return 0
    load_checkpoint_ema(ema, folder)
    step = int(load_accelerate_checkpoint(accelerator, folder)["step"])
    log(f"resumed from {folder} at step {step}")
    return step


def optimizer_step(accelerator: Accelerator, optimizer: torch.optim.Optimizer,
                   lr_schedule: torch.optim.lr_scheduler.LRScheduler, ema: EMA, module: nn.Module, loss: Tensor,
                   max_grad_norm: float | None) -> None:
    """Backward pass of ``loss``; the optimiser's gradients scaled to a global L2 norm of at most ``max_grad_norm``
    (``g <- g min(1, c / ||g||_2)``; ``None``: not clipped); optimiser and learning-rate steps; gradients cleared;
    ``module``'s weights blended into ``ema``."""
    accelerator.backward(loss)
    if max_grad_norm is not None:
        accelerator.clip_grad_norm_([p for group in optimizer.param_groups for p in group["params"]], max_grad_norm)
    optimizer.step()
    lr_schedule.step()
    optimizer.zero_grad(set_to_none=True)
    ema.update(module)


def run_steps(out: Path, config: LoopSettings, start: int, deadline: Deadline, accelerator: Accelerator,
              module: nn.Module, ema: EMA, step: Callable[[int], tuple[Tensor, dict[str, float]]],
              learning_rate: Callable[[], float], save_model: Callable[[Path], Path],
              log: Callable[[str], None]) -> Path:
    """Steps ``start .. config.steps - 1`` (``step(i)`` trains step ``i``: its loss and named loss terms), then the
    EMA weights saved by ``save_model(out/model)``; returns that folder.

    Every ``log_every`` steps, at the last one and when ``deadline`` has passed, a record (``step``, ``loss``, the
    terms, ``lr``, ``seconds`` of the step, ``elapsed_s`` since the call's start) is appended to :data:`LOG`; every
    ``checkpoint_every`` steps, at the last one and when the deadline has passed, a checkpoint is written (the newest
    ``keep_checkpoints`` kept). A passed deadline stops the loop after its checkpoint.
    """
    for index in range(start, config.steps):
        began = time.perf_counter()
        loss, terms = step(index)
        done = index + 1
        out_of_time = deadline.passed()
        last = done == config.steps or out_of_time
        if done % config.log_every == 0 or last:
            record = {"step": done, "loss": float(loss.detach()), **terms, "lr": learning_rate(),
                      "seconds": time.perf_counter() - began, "elapsed_s": deadline.elapsed()}
            with open(out / LOG, "a") as handle:
                handle.write(json.dumps(record) + "\n")
            log(" ".join([f"step {done}/{config.steps} loss {record['loss']:.4f}",
                          *(f"{name} {value:.4g}" for name, value in terms.items())]))
        if done % config.checkpoint_every == 0 or last:
            save_accelerate_checkpoint(accelerator, out / CHECKPOINTS, done, keep=config.keep_checkpoints)
        if out_of_time:
            log(f"time limit of {config.time_limit_s:g} s reached at step {done}")
            break
    with ema.averaged(module):
        return save_model(out / MODEL)
