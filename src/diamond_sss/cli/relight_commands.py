"""``diamond-sss finetune-relight | relight``: train the relighting diffusion model and relight a view."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console


def finetune_relight(out: Path, steps: int = 2000, batch_size: int = 8, learning_rate: float = 5e-4,
                     seed: int = 0, pretrained_sd: Path | None = None, init: Path | None = None,
                     data: list[Path] | None = None, resolution: int = 64, use_source_light: bool = False,
                     lpips_weights: str | None = None, mixed_precision: str = "no",
                     time_limit_s: float | None = None, checkpoint_every: int = 100, resume: bool = True,
                     quiet: bool = False) -> None:
    """Fine-tune the relighting diffusion model on the embedded fine-tuning objects (view fixed, <= 7%).

    Writes <out>/model (config.json + model.safetensors, the EMA weights), <out>/checkpoints/step_*,
    <out>/log.jsonl, <out>/selection.json (the images used) and <out>/train_config.json.

    Args:
        out: run folder.
        steps: optimisation steps.
        batch_size: (source, target) light pairs per step.
        learning_rate: AdamW peak learning rate.
        seed: seed of the initialisation, batches and noise.
        pretrained_sd: local Stable Diffusion folder (diffusers format): latent-space model (paper's route).
        init: start from the weights of a relighting model folder (config.json + model.safetensors).
        data: data folders to use instead of the embedded fine-tuning objects.
        resolution: model resolution in pixels (pixel-space default model: 64).
        use_source_light: also condition on the source light's code.
        lpips_weights: LPIPS (VGG) weights in safetensors; the LPIPS term is skipped without them.
        mixed_precision: no | fp16 | bf16 (GPU only).
        time_limit_s: stop after this much wall time (checkpoint and weights are written).
        checkpoint_every: steps between atomic checkpoints.
        resume: continue from the newest checkpoint in <out>/checkpoints.
        quiet: no log lines.
    """
    from diamond_sss.diffusion.relight.config import RelightModelConfig
    from diamond_sss.diffusion.relight.data import load_finetune_views, load_relight_views
    from diamond_sss.diffusion.relight.model import RelightDiffusion
    from diamond_sss.diffusion.relight.train import RelightTrainConfig, finetune
    from diamond_sss.losses.lpips import load_lpips

    model_config = RelightModelConfig(resolution=resolution, use_source_light=use_source_light)
    if init is not None:
        model = RelightDiffusion.load(init)
    elif pretrained_sd is not None:
        model = RelightDiffusion.from_pretrained_sd(pretrained_sd, model_config, seed=seed)
    else:
        model = RelightDiffusion.from_config(model_config, seed=seed)
    views = load_relight_views(list(data), model.config.resolution) if data else \
        load_finetune_views(model.config.resolution)
    config = RelightTrainConfig(steps=steps, batch_size=batch_size, learning_rate=learning_rate, seed=seed,
                                mixed_precision=mixed_precision, time_limit_s=time_limit_s,
                                checkpoint_every=checkpoint_every)
    console = Console()
    lpips = load_lpips(lpips_weights)

    def log(record: dict) -> None:
        if not quiet:
            console.print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in record.items()))

    folder = finetune(views, out, model, config, lpips=lpips, resume=resume, log=log)
    console.print(f"relighting model -> {folder}")
