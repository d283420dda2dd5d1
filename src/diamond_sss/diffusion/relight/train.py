"""Fine-tuning loop of the relighting model (accelerate, EMA, atomic checkpoints, resume)."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import torch
from torch import Tensor, nn

from diamond_sss.diffusion.common.ema import EMA, save_ema_with_checkpoints
from diamond_sss.diffusion.common.finetune import (
    check_loop_settings,
    open_run,
    optimizer_step,
    resume_from,
    run_steps,
)
from diamond_sss.diffusion.common.hashing import state_dict_hash
from diamond_sss.diffusion.common.runtime import (
    Deadline,
    deterministic_kernels,
    fused_adamw,
    make_accelerator,
)
from diamond_sss.diffusion.common.targets import predicted_clean, v_target
from diamond_sss.diffusion.relight.augment import augment_batch
from diamond_sss.diffusion.relight.config import RelightLossWeights, RelightTrainConfig
from diamond_sss.diffusion.relight.data import RelightViews
from diamond_sss.diffusion.relight.losses import image_losses
from diamond_sss.diffusion.relight.model import RelightDiffusion
from diamond_sss.utils.device import to_device
from diamond_sss.utils.io import atomic_write_json

RESUMABLE = ("checkpoint_every", "keep_checkpoints", "log_every", "time_limit_s")
"""``RelightTrainConfig`` fields a resumed run may change: logging, checkpointing and its wall-time limit. Not
``steps``: the cosine decay of the learning rate spans them, so more steps would change the rate of steps already
scheduled."""
IMPLIED = {"max_grad_norm": 1.0}
"""Settings added since older runs were recorded, as those runs trained: gradients clipped to norm 1."""


def step_generator(seed: int, step: int) -> torch.Generator:
    """CPU generator of one step's random draws (a pure function of seed and step, so resume is exact)."""
    return torch.Generator().manual_seed(seed * 1_000_003 + step)


def training_loss(
    model: RelightDiffusion,
    batch: dict[str, Tensor],
    weights: RelightLossWeights,
    generator: torch.Generator,
    with_cycle: bool,
    lpips: nn.Module | None = None,
) -> tuple[Tensor, dict[str, float]]:
    """Total loss of one batch (see ``losses.py``) and its unweighted terms.

    Timesteps and noise come from ``generator`` (CPU) and are moved to the batch's device.
    """
    device = batch["target"].device
    hint = model.hint(batch["conditioning"], batch["target_code"], batch["source_code"])
    offset = model.offset(hint)
    target = model.encode(batch["target"])
    if offset is not None:
        target = target - offset
    count = target.shape[0]
    alphas = model.alphas_cumprod
    timesteps = torch.randint(0, alphas.shape[0], (count,), generator=generator).to(device)
    noise = torch.randn(target.shape, generator=generator).to(device=device, dtype=target.dtype)
    noisy = model.train_scheduler.add_noise(target, noise, timesteps)
    v = model(noisy, timesteps, batch["conditioning"], batch["target_code"], batch["source_code"], hint=hint)
    terms = {"v_mse": (v.float() - v_target(target, noise, alphas, timesteps)).square().mean()}
    clean = model.decode(with_offset(predicted_clean(noisy, v.float(), alphas, timesteps), offset))
    terms.update(image_losses(clean, batch["target"], weights, lpips))
    if with_cycle:
        back_conditioning = torch.cat([clean, batch["maps"]], dim=1)
        back_hint = model.hint(back_conditioning, batch["source_code"], batch["target_code"])
        back_offset = model.offset(back_hint)
        source = with_offset(model.encode(batch["source"]), back_offset, sign=-1.0)
        back_noise = torch.randn(source.shape, generator=generator).to(device=device, dtype=source.dtype)
        back_noisy = model.train_scheduler.add_noise(source, back_noise, timesteps)
        back_v = model(
            back_noisy, timesteps, back_conditioning, batch["source_code"], batch["target_code"], hint=back_hint
        )
        back_clean = model.decode(
            with_offset(predicted_clean(back_noisy, back_v.float(), alphas, timesteps), back_offset)
        )
        terms["cycle"] = (back_clean - batch["source"]).abs().mean()
    total = sum(getattr(weights, name) * value for name, value in terms.items())
    return total, {name: float(value.detach()) for name, value in terms.items()}


def with_offset(sample: Tensor, offset: Tensor | None, sign: float = 1.0) -> Tensor:
    """``sample + sign * offset`` (``sample`` itself when the model is not residual)."""
    return sample if offset is None else sample + sign * offset


def lr_factor(step: int, warmup: int, total: int) -> float:
    """Linear warm-up to 1, then cosine decay to 0.1 at ``total``."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return 0.1 + 0.45 * (1.0 + math.cos(math.pi * progress))


@deterministic_kernels
def finetune(
    views: RelightViews,
    out: str | os.PathLike,
    model: RelightDiffusion,
    config: RelightTrainConfig,
    lpips: nn.Module | None = None,
    resume: bool = True,
    log: Callable[[str], None] = print,
) -> Path:
    """Fine-tune ``model`` on ``views``; returns ``out/model``, the EMA weights (see :meth:`RelightDiffusion.save`).

    The run folder is the fine-tunes' common one (``diffusion/common/finetune.py``): ``finetune_config.json`` the
    ``RelightTrainConfig``, the model's config (``model``) and the content hashes of the training views
    (``data_hash``) and of the LPIPS network (``lpips_hash``, null without one); ``train_log.jsonl`` the loss, its
    terms, learning rate and seconds per logged step; ``checkpoints/step_<N>``; and ``selection.json``, the images
    used. With ``resume`` the newest complete checkpoint is restored (model, optimizer, schedule, EMA) and training
    continues from its step with the same batches it would have drawn; the settings must be the recorded ones but
    for the :data:`RESUMABLE` fields (others are refused, naming them).
    """
    check_loop_settings(config)
    deadline = Deadline(config.time_limit_s)
    out = Path(out)
    settings = {**asdict(config), "model": model.config.to_dict(), "data_hash": state_dict_hash(asdict_views(views)),
                "lpips_hash": None if lpips is None else state_dict_hash(lpips.state_dict())}
    found = open_run(out, settings, RESUMABLE, IMPLIED, resume, log)
    atomic_write_json(out / "selection.json", views.selection)
    accelerator = make_accelerator(config.mixed_precision)
    trainable = [p for p in model.parameters() if p.requires_grad]
    optimizer = fused_adamw(trainable, config.learning_rate, config.weight_decay)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda step: lr_factor(step, config.warmup_steps, config.steps)
    )
    model, optimizer, schedule = accelerator.prepare(model, optimizer, schedule)
    unwrapped = accelerator.unwrap_model(model)
    ema = EMA(unwrapped, decay=config.ema_decay)
    save_ema_with_checkpoints(accelerator, ema)
    if lpips is not None:
        lpips = lpips.to(accelerator.device).requires_grad_(False)
    start = resume_from(accelerator, ema, found, log)
    device = accelerator.device
    data = {k: v.to(device) for k, v in asdict_views(views).items()}
    on_device = RelightViews(**data, selection=views.selection)
    model.train()

    def step(index: int) -> tuple[Tensor, dict[str, float]]:
        generator = step_generator(config.seed, index)
        batch = on_device.batch(*[to_device(i, device) for i in views.random_indices(config.batch_size, generator)])
        batch = augment_batch(batch, config.augment, generator)
        with accelerator.autocast():
            loss, terms = training_loss(
                unwrapped,
                batch,
                config.losses,
                generator,
                with_cycle=config.cycle_every > 0 and index % config.cycle_every == 0,
                lpips=lpips,
            )
        optimizer_step(accelerator, optimizer, schedule, ema, unwrapped, loss, config.max_grad_norm)
        return loss, terms

    return run_steps(out, config, start, deadline, accelerator, unwrapped, ema, step,
                     lambda: schedule.get_last_lr()[0], unwrapped.save, log)


def asdict_views(views: RelightViews) -> dict[str, Tensor]:
    """The tensor fields of ``views``."""
    return {
        "maps": views.maps,
        "images": views.images,
        "sources": views.sources,
        "codes": views.codes,
        "light_counts": views.light_counts,
    }
