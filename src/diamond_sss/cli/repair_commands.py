"""``diamond-sss repair-data | repair-train``: training pairs and training of the render-repair model (issue 59)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console

from diamond_sss.cli.options import config_from, options_of
from diamond_sss.diffusion.repair.config import RepairModelConfig, RepairTrainConfig

RepairTrainOptions = options_of(RepairTrainConfig)
RepairModelOptions = options_of(RepairModelConfig)


def repair_data(run: list[Path], out: Path, data: Path | None = None, lattice: Path | None = None,
                split: str = "train", most: int = 200, seed: int = 0, quiet: bool = False) -> None:
    """Write the repair model's training pairs of finished sparse reconstructions: each run rendered at the images
    of its capture it did not see (input: render, G-buffer, warped nearest real image, light code), against the true
    images. One file per run, <out>/<run folder name>.safetensors; an existing file is kept.

    Args:
        run: finished `diamond-sss train` run folders (their data.json names the capture).
        out: folder of the pair files.
        data: the capture, when the runs' data.json does not name it (the same for every run).
        lattice: a twin of the capture (its rig and seed, other intrinsics: e.g. framed at the object as the
            pipeline's generated cameras are) whose images the pairs are made at.
        split: the capture's split the runs trained on.
        most: at most this many pairs per run, a seeded draw (0: every unseen image).
        seed: seed of that draw.
        quiet: no progress bars.
    """
    from diamond_sss.diffusion.repair.data import write_pairs

    console = Console()
    for folder in run:
        path = Path(out) / f"{Path(folder).name}.safetensors"
        if path.is_file():
            console.print(f"{path}: exists, kept")
            continue
        write_pairs(folder, path, data=data, lattice=lattice, split=split, most=most, seed=seed, show_progress=not quiet)
        console.print(f"repair pairs -> {path}")


def repair_train(
    pairs: list[Path],
    out: Path,
    init: Path | None = None,
    resume: bool = True,
    quiet: bool = False,
    training: Annotated[RepairTrainOptions, tyro.conf.OmitArgPrefixes] = RepairTrainOptions(),  # noqa: B008
    model: Annotated[RepairModelOptions, tyro.conf.OmitArgPrefixes] = RepairModelOptions(),  # noqa: B008
) -> None:
    """Train the render-repair model on pair files of `diamond-sss repair-data`. Writes <out>/model (config.json +
    model.safetensors, the EMA weights: give it to `run --augment repair --repair-model`), <out>/checkpoints/step_*,
    <out>/train_log.jsonl, <out>/finetune_config.json and, with held-out files, <out>/validation.json (the repaired
    images' PSNR beside the renders').

    Args:
        pairs: pair files (.safetensors); the first validation_files are held out.
        out: run folder.
        init: start from the weights of a repair model folder.
        resume: continue from the newest checkpoint in <out>/checkpoints.
        quiet: no log lines.
        training: training settings (RepairTrainConfig).
        model: the network's settings (RepairModelConfig; ignored with --init).
    """
    from diamond_sss.diffusion.repair.model import RepairModel
    from diamond_sss.diffusion.repair.train import train_repair

    console = Console()
    folder = train_repair(pairs, out, config_from(RepairTrainConfig, training),
                          model=RepairModel.load(init) if init is not None else None,
                          model_config=config_from(RepairModelConfig, model), resume=resume,
                          log=(lambda _: None) if quiet else console.print)
    console.print(f"repair model -> {folder}")
