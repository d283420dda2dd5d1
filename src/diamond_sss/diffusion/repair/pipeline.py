"""Inference of the repair model: the repaired images of (view, light) targets written as a generated-image folder
(``images/``, ``masks/``, ``manifest.json``: :mod:`~diamond_sss.diffusion.common.manifest`)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import torch
from tqdm.auto import tqdm

from diamond_sss.data.conventions import srgb_to_linear
from diamond_sss.data.images import to_srgb8, write_png
from diamond_sss.diffusion.common.manifest import GeneratedImage, image_paths, write_image_manifest
from diamond_sss.diffusion.common.paths import shipped_model_dir
from diamond_sss.diffusion.repair.inputs import RepairInputs
from diamond_sss.diffusion.repair.model import RepairModel
from diamond_sss.errors import DataError


def default_model_dir() -> Path:
    """The shipped repair model's folder (``assets/models/repair``)."""
    return shipped_model_dir("repair")


def load_repair_model(folder: str | os.PathLike | None, device: str | torch.device = "cpu") -> RepairModel:
    """The repair model in ``folder`` (default: the shipped one); a missing one is an error naming the fix."""
    folder = Path(folder) if folder is not None else default_model_dir()
    if not (folder / "model.safetensors").is_file():
        raise DataError(f"no repair model in {folder} (model.safetensors missing): train one with `diamond-sss "
                        "repair-data` and `diamond-sss repair-train`, then give its folder with --repair-model")
    return RepairModel.load(folder, device)


@torch.no_grad()
def repair_targets(model: RepairModel, builder: RepairInputs, targets: Sequence[tuple[int, int]],
                   out: str | os.PathLike, batch_size: int = 16, show_progress: bool = True) -> list[GeneratedImage]:
    """Repair the render of every ``(view, light)`` target and write it to ``out`` as ``v<view>_l<light>``; returns
    the written images (also listed in ``out/manifest.json``)."""
    out = Path(out)
    device = next(model.parameters()).device
    written = []
    chunks = [targets[i:i + batch_size] for i in range(0, len(targets), batch_size)]
    for chunk in tqdm(chunks, desc="repair", unit="batch", disable=not show_progress, dynamic_ncols=True):
        inputs = torch.stack([builder.target(view, light)[0] for view, light in chunk]).to(device)
        for (view, light), image in zip(chunk, model(inputs).cpu(), strict=True):
            item = GeneratedImage(view, light, *image_paths(out, f"v{view:03d}_l{light:03d}"))
            alpha = image[3:].permute(1, 2, 0)
            write_png(item.image, to_srgb8(srgb_to_linear(image[:3].permute(1, 2, 0)), alpha))
            write_png(item.mask, (alpha[..., 0].numpy() * 255.0 + 0.5).astype("uint8"))
            written.append(item)
    write_image_manifest(out, written)
    return written
