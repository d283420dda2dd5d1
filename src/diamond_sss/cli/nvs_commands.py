"""``diamond-sss finetune-nvs | nvs``: fine-tune and run the novel-view diffusion model."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console


def finetune_nvs(out: Path, data: list[Path] | None = None, steps: int = 1000, objects_per_batch: int = 4,
                 views_per_object: int = 4, learning_rate: float = 1e-4, warmup_steps: int = 100,
                 image_size: int = 32, space: str = "pixel", vae: Path | None = None,
                 gradient_checkpointing: bool = True, checkpoint_every: int = 200, seed: int = 0,
                 resume: bool = True) -> None:
    """Fine-tune the Free3D-style novel-view model on fixed-illumination multi-view sequences.

    Writes <out>/model (config.json + model.safetensors, EMA weights), checkpoints and train_log.jsonl.

    Args:
        out: run folder.
        data: OLAT data folders (default: the embedded fine-tuning objects).
        steps: optimisation steps.
        objects_per_batch: objects per step (one sequence each).
        views_per_object: target views per object (all share one timestep).
        learning_rate: AdamW learning rate after warm-up.
        warmup_steps: linear warm-up steps.
        image_size: side of the generated images (pixels; latent space: 8x the latent side).
        space: pixel (small offline default) or latent (needs --vae).
        vae: local diffusers AutoencoderKL folder for latent space.
        gradient_checkpointing: recompute activations of every ResNet/transformer block in the backward pass.
        checkpoint_every: steps between atomic checkpoints.
        seed: seed of the model initialisation and of the sampled training stream.
        resume: continue from the newest checkpoint in --out.
    """
    from diamond_sss.data.embedded import FINETUNE_PREFIX, embedded_dataset, embedded_dataset_names
    from diamond_sss.diffusion.nvs.model import NVSConfig
    from diamond_sss.diffusion.nvs.train import FinetuneConfig, finetune

    if data is None:
        names = [n for n in embedded_dataset_names() if n.startswith(FINETUNE_PREFIX)]
        data = [embedded_dataset(n) for n in names]
    if not data:
        raise ValueError("no fine-tuning data: pass --data or install the embedded fine-tuning objects")
    model = NVSConfig(space=space, image_size=image_size, vae_path=None if vae is None else str(vae))
    config = FinetuneConfig(steps=steps, objects_per_batch=objects_per_batch, views_per_object=views_per_object,
                            learning_rate=learning_rate, warmup_steps=warmup_steps,
                            gradient_checkpointing=gradient_checkpointing, checkpoint_every=checkpoint_every,
                            seed=seed, model=model)
    console = Console()
    folder = finetune(data, out, config, resume=resume, log=console.print)
    console.print(f"model -> {folder}")
