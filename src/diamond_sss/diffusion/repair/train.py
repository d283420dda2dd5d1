"""Training loop of the repair model (the fine-tunes' loop: accelerate, EMA, atomic checkpoints, exact resume).

Loss of a batch of crops: ``mean |y_rgb - t_rgb| + alpha_weight mean |y_alpha - t_alpha|`` (premultiplied sRGB and
alpha in [0, 1], :mod:`.model`). The first ``validation_files`` pair files are held out: the end of a run writes
``validation.json``, the repaired images' PSNR against the truth beside the renders' own.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import torch
from torch import Tensor

from diamond_sss.diffusion.common.ema import EMA, save_ema_with_checkpoints
from diamond_sss.diffusion.common.finetune import (
    check_loop_settings,
    open_run,
    optimizer_step,
    resume_from,
    run_steps,
)
from diamond_sss.diffusion.common.runtime import (
    Deadline,
    deterministic_kernels,
    fused_adamw,
    make_accelerator,
)
from diamond_sss.diffusion.relight.train import RESUMABLE, lr_factor, step_generator
from diamond_sss.diffusion.repair.config import RepairModelConfig, RepairTrainConfig
from diamond_sss.diffusion.repair.data import RepairPairs
from diamond_sss.diffusion.repair.model import RepairModel
from diamond_sss.utils.io import atomic_write_json, sha256_file, sha256_json


def repair_loss(model: RepairModel, inputs: Tensor, targets: Tensor, alpha_weight: float) -> tuple[Tensor, dict]:
    """The loss above and its two terms."""
    output = model(inputs)
    rgb = (output[:, :3] - targets[:, :3]).abs().mean()
    alpha = (output[:, 3:] - targets[:, 3:]).abs().mean()
    return rgb + alpha_weight * alpha, {"rgb_l1": float(rgb.detach()), "alpha_l1": float(alpha.detach())}


def psnr_each(images: Tensor, targets: Tensor) -> Tensor:
    """PSNR (dB) of each premultiplied sRGB image ``[N, >=3, H, W]`` against its target, over its whole frame."""
    mse = (images[:, :3] - targets[:, :3]).square().flatten(1).mean(1)
    return -10.0 * torch.log10(mse.clamp_min(1e-12))


@torch.no_grad()
def validation(model: RepairModel, pairs: RepairPairs, chunk: int = 32) -> dict[str, float]:
    """Mean PSNR of the renders (the inputs' first channels) and of the repaired images against the truth, and
    the share of images the repair improves."""
    model.eval()
    device = next(model.parameters()).device
    repaired = torch.cat([model(pairs.inputs[i:i + chunk].to(device)).cpu() for i in range(0, len(pairs), chunk)])
    render, fixed = psnr_each(pairs.inputs, pairs.targets), psnr_each(repaired, pairs.targets)
    return {"pairs": len(pairs), "render_psnr": round(float(render.mean()), 3),
            "repaired_psnr": round(float(fixed.mean()), 3), "better": round(float((fixed > render).float().mean()), 3)}


@deterministic_kernels
def train_repair(pair_files: Sequence[str | os.PathLike], out: str | os.PathLike, config: RepairTrainConfig,
                 model: RepairModel | None = None, model_config: RepairModelConfig | None = None,
                 resume: bool = True, log: Callable[[str], None] = print) -> Path:
    """Train ``model`` (default: a new one of ``model_config``, seeded by ``config.seed``) on the pairs of ``pair_files`` but the first
    ``validation_files``; returns ``out/model`` (the EMA weights). The run folder is the fine-tunes' common one."""
    check_loop_settings(config)
    files = [str(Path(p).resolve()) for p in pair_files]
    held, used = files[:config.validation_files], files[config.validation_files:]
    if not used:
        raise ValueError(f"repair training: {len(files)} pair file(s), all held out for validation "
                         f"(validation_files {config.validation_files}); give more")
    if model is None:
        torch.manual_seed(config.seed)
        model = RepairModel(model_config)
    out = Path(out)
    settings = {**asdict(config), "model": asdict(model.config), "train_files": used, "validation_files": held,
                "data_hash": sha256_json([sha256_file(f) for f in files])}
    found = open_run(out, settings, RESUMABLE, {}, resume, log)
    pairs = RepairPairs.read(used)
    log(f"repair training: {len(pairs)} pairs from {len(used)} file(s), {len(held)} held out")
    accelerator = make_accelerator("no")
    optimizer = fused_adamw(model.parameters(), config.learning_rate, config.weight_decay)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: lr_factor(s, config.warmup_steps, config.steps))
    model, optimizer, schedule = accelerator.prepare(model, optimizer, schedule)
    unwrapped = accelerator.unwrap_model(model)
    ema = EMA(unwrapped, decay=config.ema_decay)
    save_ema_with_checkpoints(accelerator, ema)
    start = resume_from(accelerator, ema, found, log)
    device = accelerator.device
    unwrapped.train()

    def step(index: int) -> tuple[Tensor, dict[str, float]]:
        inputs, targets = pairs.batch(config.batch_size, config.crop, step_generator(config.seed, index),
                                      zoom_out=config.zoom_out)
        loss, terms = repair_loss(unwrapped, inputs.to(device), targets.to(device), config.alpha_weight)
        optimizer_step(accelerator, optimizer, schedule, ema, unwrapped, loss, config.max_grad_norm)
        return loss, terms

    folder = run_steps(out, config, start, Deadline(config.time_limit_s), accelerator, unwrapped, ema, step,
                       lambda: schedule.get_last_lr()[0], unwrapped.save, log)
    if held and (folder / "model.safetensors").is_file():
        result = validation(RepairModel.load(folder, device), RepairPairs.read(held))
        atomic_write_json(out / "validation.json", {**result, "files": held})
        log(f"validation ({result['pairs']} pairs): render {result['render_psnr']:.2f} dB, repaired "
            f"{result['repaired_psnr']:.2f} dB")
    return folder

