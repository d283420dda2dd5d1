"""Speed of the novel-view fine-tune's step (``diamond-sss finetune-nvs``), and where it goes.

For each objects-per-step x precision x kernel mode: the mean time of the batch (sampling on the host, copy to the
device) and of the step (loss forward, backward pass, optimiser and EMA updates), each synchronised, over
``--timed-steps`` steps after ``--warmup``; target images per second and peak GPU memory. Kernel modes: ``deterministic``
(what ``finetune-nvs`` runs: cuDNN without autotuning, deterministic algorithms) and ``autotuned`` (cuDNN autotuning,
no deterministic algorithms), so the price of reproducibility is on the table. With ``--profile``, torch.profiler's tables of
3 more steps per case (``profile_nvs_<case>.txt``: operators by self CPU / CUDA time, host syncs by call site) and
their counts. The model and the fine-tune take ``finetune-nvs``'s options; ``scripts/gpu_check.py`` passes the GPU
prior's. Writes ``nvs_speed.{json,md}`` into ``--output``.

    python benchmarks/nvs_speed.py --data outputs/priors/* --image-size 64 --block-out-channels 48 96 96 \\
        --layers-per-block 2 --prediction-type v_prediction --hint-residual --no-gradient-checkpointing --profile
"""

from __future__ import annotations

import dataclasses
import json
import platform
import statistics
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Literal

import torch
import tyro

from diamond_sss.cli.nvs_commands import FinetuneOptions, NVSModelOptions, model_config
from diamond_sss.cli.options import config_from
from diamond_sss.data.embedded import embedded_dataset, finetune_object_names
from diamond_sss.diffusion.common.runtime import kernel_settings
from diamond_sss.diffusion.nvs.config import FinetuneConfig
from diamond_sss.diffusion.nvs.train import build_training, step_batch, training_step
from diamond_sss.errors import DataError
from diamond_sss.utils.profiling import profile_steps, synchronize

RESULTS = Path(__file__).resolve().parent / "results" / "nvs_speed"
PROFILE_STEPS = 3
"""Steps profiled per case with ``--profile``."""

KernelMode = Literal["deterministic", "autotuned"]


def time_case(data: list[Path], config: FinetuneConfig, kernels: KernelMode, steps: int, warmup: int,
              profile_dir: Path | None = None) -> dict:
    """One case: mean batch and step milliseconds over ``steps`` steps after ``warmup``, images per second, peak GPU
    memory (GiB, CUDA only) and, with ``profile_dir``, :func:`profile_steps` of the next steps."""
    with kernel_settings(deterministic=kernels == "deterministic"):
        row = _measure(data, config, steps, warmup, profile_dir, kernels)
    images = config.objects_per_batch * config.views_per_object
    return {"objects": config.objects_per_batch, "images": images, "precision": config.mixed_precision,
            "kernels": kernels, **row, "images_per_second": 1e3 * images / (row["batch_ms"] + row["step_ms"])}


def _measure(data: list[Path], config: FinetuneConfig, steps: int, warmup: int, profile_dir: Path | None,
             kernels: str) -> dict:
    state = build_training(data, config)
    device = state.accelerator.device
    state.model.train()
    for step in range(warmup):
        training_step(state, config, step_batch(state, config, step), step)
    synchronize(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    batch_ms, step_ms = [], []
    for step in range(warmup, warmup + steps):
        start = time.perf_counter()
        batch = step_batch(state, config, step)
        synchronize(device)
        middle = time.perf_counter()
        training_step(state, config, batch, step)
        synchronize(device)
        batch_ms.append(1e3 * (middle - start))
        step_ms.append(1e3 * (time.perf_counter() - middle))
    row = {"device": device.type, "batch_ms": statistics.mean(batch_ms), "step_ms": statistics.mean(step_ms),
           "peak_gib": torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None}
    if profile_dir is not None:
        name = f"profile_nvs_{device.type}_{config.objects_per_batch}obj_{config.mixed_precision}_{kernels}.txt"
        row |= profile_steps(lambda i: training_step(state, config, step_batch(state, config, i), i), device,
                             warmup + steps, PROFILE_STEPS, profile_dir / name)
    return row


def run(
    data: list[Path] | None = None,
    objects: tuple[int, ...] = (4, 8),
    precisions: tuple[Literal["no", "fp16", "bf16"], ...] = ("no", "bf16"),
    kernels: tuple[KernelMode, ...] = ("deterministic", "autotuned"),
    timed_steps: int = 10,
    warmup: int = 3,
    profile: bool = False,
    output: Path = RESULTS,
    training: Annotated[FinetuneOptions, tyro.conf.OmitArgPrefixes] = FinetuneOptions(),  # noqa: B008
    model: Annotated[NVSModelOptions, tyro.conf.OmitArgPrefixes] = NVSModelOptions(),  # noqa: B008
) -> list[dict]:
    """Time the fine-tune's step for every objects x precision x kernels case; write and print the table.

    Args:
        data: OLAT data folders (default: the embedded fine-tuning objects).
        objects: objects per step to time (each with ``--views-per-object`` target views).
        precisions: autocast settings to time (``fp16`` needs CUDA).
        kernels: kernel modes to time: ``deterministic`` (as ``finetune-nvs``) and ``autotuned``.
        timed_steps: timed steps per case.
        warmup: steps before the timed ones (cuDNN autotuning, allocator, autocast caches).
        profile: also profile 3 steps per case (operators, CUDA kernels, host syncs).
        output: folder of nvs_speed.{json,md} and the profiles.
        training: fine-tuning settings (as ``finetune-nvs``).
        model: the model's settings (as ``finetune-nvs``).
    """
    if timed_steps < 1 or warmup < 0:
        raise ValueError(f"--timed-steps must be >= 1 and --warmup >= 0, got {timed_steps} and {warmup}")
    data = data or [embedded_dataset(n) for n in finetune_object_names()]
    base = config_from(FinetuneConfig, training, model=model_config(model, None, None, training.init_from))
    rows = []
    for count in objects:
        for precision in precisions:
            for mode in kernels:
                config = dataclasses.replace(base, objects_per_batch=count, mixed_precision=precision)
                rows.append(time_case(data, config, mode, timed_steps, warmup, output if profile else None))
                print(table_row(rows[-1]), flush=True)
    meta = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "torch": torch.__version__,
            "threads": torch.get_num_threads(), "machine": platform.machine(),
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "model": dataclasses.asdict(base.model), "views_per_object": base.views_per_object,
            "timed_steps": timed_steps}
    table = markdown(rows)
    print(table)
    output.mkdir(parents=True, exist_ok=True)
    (output / "nvs_speed.json").write_text(json.dumps({"meta": meta, "results": rows}, indent=2) + "\n")
    (output / "nvs_speed.md").write_text(f"{json.dumps({k: v for k, v in meta.items() if k != 'model'})}\n\n{table}\n")
    return rows


HEADER = ("| device | objects | images | precision | kernels | batch ms | step ms | images/s | peak GiB "
          "| operators / step | CUDA kernels / step | host syncs / step |")


def table_row(r: dict) -> str:
    """One case as a Markdown table row (profile counts ``-`` when not profiled)."""
    counts = [f"{r[k]:.0f}" if k in r else "-" for k in ("operators_per_step", "cuda_kernels_per_step")]
    syncs = f"{r['host_syncs_per_step']:.1f}" if "host_syncs_per_step" in r else "-"
    peak = f"{r['peak_gib']:.2f}" if r["peak_gib"] is not None else "-"
    return (f"| {r['device']} | {r['objects']} | {r['images']} | {r['precision']} | {r['kernels']} "
            f"| {r['batch_ms']:.1f} | {r['step_ms']:.1f} | {r['images_per_second']:.1f} | {peak} "
            f"| {counts[0]} | {counts[1]} | {syncs} |")


def markdown(rows: list[dict]) -> str:
    """The cases as a Markdown table."""
    return "\n".join([HEADER, "|" + "---|" * HEADER.count(" | ") + "---|", *map(table_row, rows)])


if __name__ == "__main__":
    try:
        tyro.cli(run)
    except DataError as exc:
        raise SystemExit(f"nvs_speed: --data: {exc}") from exc
