"""Fine-tuning loop of the novel-view model (accelerate, EMA, atomic checkpoints, resume).

Defaults follow supplement Sec. C.2: 16 target views from 4 objects per step, AdamW at ``1e-4`` with 100
linear warm-up steps, gradient checkpointing. Sampling of the training stream is a pure function of
``(seed, step)``, so a resumed run continues exactly where the interrupted one stopped.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from accelerate import Accelerator
from diffusers import DDPMScheduler
from diffusers.optimization import get_constant_schedule_with_warmup
from torch import Tensor

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
from diamond_sss.diffusion.common.schedulers import make_ddpm_scheduler
from diamond_sss.diffusion.nvs.config import FinetuneConfig
from diamond_sss.diffusion.nvs.data import Sequence, fixed_light_sequences, sample_batch
from diamond_sss.diffusion.nvs.depth_noise import perturb_depth
from diamond_sss.diffusion.nvs.model import NVSBatch, NVSModel
from diamond_sss.utils.device import to_device

RESUMABLE = ("steps", "checkpoint_every", "keep_checkpoints", "log_every", "time_limit_s", "gradient_checkpointing")
"""``FinetuneConfig`` fields a resumed run may change: its length (the learning rate is constant after the warm-up,
so more steps continue the same run), logging, checkpointing, and recomputing activations (the same gradients)."""
IMPLIED = {"max_grad_norm": None}
"""Settings added since older runs were recorded, as those runs trained: no gradient clipping."""


@dataclass
class TrainingState:
    """What the steps of a fine-tune read and update, on ``accelerator.device``: the model as accelerate prepared it
    and the module itself (``raw``), optimiser, learning-rate schedule, EMA of the weights, the DDPM noise schedule
    and the training sequences (on the host)."""

    accelerator: Accelerator
    model: torch.nn.Module
    raw: NVSModel
    optimizer: torch.optim.Optimizer
    lr_schedule: torch.optim.lr_scheduler.LRScheduler
    ema: EMA
    noise_schedule: DDPMScheduler
    sequences: list[Sequence]


def build_training(data: list[str | Path], config: FinetuneConfig) -> TrainingState:
    """Model (seeded by ``config.seed``; from ``config.init_from``'s weights when given), data and optimiser of a
    fine-tune, prepared by accelerate. Writes nothing."""
    torch.manual_seed(config.seed)
    accelerator = make_accelerator(config.mixed_precision)
    model = NVSModel(config.model)
    if config.init_from is not None:
        model.load_weights_from(config.init_from)
    if config.gradient_checkpointing:
        model.enable_gradient_checkpointing()
    warp = config.model.warp_hint
    size = config.model.warp_source_size if warp else config.model.image_size
    sequences = fixed_light_sequences(list(data), size, with_depth=warp)
    optimizer = fused_adamw(model.trainable_parameters(), config.learning_rate, config.weight_decay)
    lr_schedule = get_constant_schedule_with_warmup(optimizer, num_warmup_steps=config.warmup_steps)
    model, optimizer, lr_schedule = accelerator.prepare(model, optimizer, lr_schedule)
    raw = accelerator.unwrap_model(model)
    ema = EMA(raw, decay=config.ema_decay)
    save_ema_with_checkpoints(accelerator, ema)
    return TrainingState(accelerator, model, raw, optimizer, lr_schedule, ema,
                         make_ddpm_scheduler(config.model.scheduler), sequences)


def step_batch(state: TrainingState, config: FinetuneConfig, step: int) -> NVSBatch:
    """The batch of step ``step`` (a pure function of ``config.seed`` and ``step``), on the training device."""
    generator = torch.Generator().manual_seed(config.seed * 1_000_003 + step)
    batch = sample_batch(state.sequences, config.objects_per_batch, config.views_per_object, generator)
    if batch.reference_depth is not None:
        batch.reference_depth = perturb_depth(
            batch.reference_depth, generator, config.depth_noise_share, config.depth_noise_relative,
            config.depth_noise_edge_px, pixel_scale=config.model.warp_supersample,
        )
    return _to_device(batch, state.accelerator.device)


def training_step(state: TrainingState, config: FinetuneConfig, batch: NVSBatch, step: int) -> Tensor:
    """Loss of ``batch`` (autocast in ``config.mixed_precision``), backward pass, gradient clipping, optimiser and EMA
    updates (:func:`~diamond_sss.diffusion.common.finetune.optimizer_step`). Returns the loss (on the device: reading
    it waits for the GPU)."""
    with state.accelerator.autocast():
        loss = state.raw.training_loss(
            batch,
            generator=_device_generator(state.accelerator.device, config.seed, step),
            scheduler=state.noise_schedule,
        )
    optimizer_step(state.accelerator, state.optimizer, state.lr_schedule, state.ema, state.raw, loss,
                   config.max_grad_norm)
    return loss


@deterministic_kernels
def finetune(
    data: list[str | Path],
    out: str | Path,
    config: FinetuneConfig | None = None,
    resume: bool = True,
    log: Callable[[str], None] = print,
) -> Path:
    """Fine-tune on the fixed-illumination sequences of ``data``; write ``out/model`` (EMA weights).

    Returns the model folder. The run folder is the fine-tunes' common one (``diffusion/common/finetune.py``):
    ``finetune_config.json`` the settings and ``data_hash``, the content hash of the training sequences;
    ``train_log.jsonl`` loss, learning rate and seconds per logged step; ``checkpoints/step_<N>``. With
    ``config.time_limit_s`` the run stops at the first step past that wall time (counted from the call, loading
    included), checkpointed; running it again with the same ``out`` resumes it, with the same settings and data but
    for the :data:`RESUMABLE` fields (others are refused, naming them). ``config.init_from`` starts a new run from a
    saved model's weights (the EMA too); a resumed run takes its checkpoint's.
    """
    config = config or FinetuneConfig()
    check_loop_settings(config)
    deadline = Deadline(config.time_limit_s)
    out = Path(out)
    state = build_training(data, config)
    settings = {**asdict(config), "data_hash": sequences_hash(state.sequences)}
    latest = open_run(out, settings, RESUMABLE, IMPLIED, resume, log)
    start = resume_from(state.accelerator, state.ema, latest, log)
    state.model.train()

    def step(index: int) -> tuple[Tensor, dict[str, float]]:
        return training_step(state, config, step_batch(state, config, index), index), {}

    return run_steps(out, config, start, deadline, state.accelerator, state.raw, state.ema, step,
                     lambda: state.lr_schedule.get_last_lr()[0], state.raw.save, log)


def sequences_hash(sequences: list[Sequence]) -> str:
    """Content hash of training sequences: each one's object name, light, views and tensors, in order."""
    tensors = {}
    for index, sequence in enumerate(sequences):
        prefix = f"{index}|{sequence.name}|{sequence.light}|{sequence.views}"
        for name in ("images", "w2c", "K", "depth"):
            if getattr(sequence, name) is not None:
                tensors[f"{prefix}|{name}"] = getattr(sequence, name)
    return state_dict_hash(tensors)


def _device_generator(device: torch.device, seed: int, step: int) -> torch.Generator:
    return torch.Generator(device=device).manual_seed(seed * 7_919 + step + 1)


def _to_device(batch, device: torch.device):
    """The batch's tensors on ``device`` (without blocking the host: :func:`~diamond_sss.utils.device.to_device`)."""
    for name in (
        "reference",
        "reference_w2c",
        "target_w2c",
        "target_K",
        "targets",
        "reference_K",
        "reference_depth",
    ):
        value = getattr(batch, name)
        if value is not None:
            setattr(batch, name, to_device(value, device))
    return batch
