"""Training pairs of the repair model: a sparse reconstruction rendered at the lattice images it did not see (the
model's input, :mod:`.inputs`) against the true images there. The lattice may be a twin capture of the same cameras
and lights with other intrinsics (e.g. framed at the object as the pipeline's generated cameras are,
:mod:`diamond_sss.pipeline.rig`), so that the pairs are made where the pipeline repairs.

A pair file (``safetensors``, written atomically) holds ``inputs [N, 23, H, W]`` and ``targets [N, 4, H, W]``
(premultiplied sRGB and alpha) in float16, and in its metadata the capture, the run and the model-hash of the
reconstruction. :class:`RepairPairs` reads several and draws seeded batches of random crops.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors import SafetensorError, safe_open
from torch import Tensor
from tqdm.auto import tqdm

from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.diffusion.repair.config import IMAGE_CHANNELS, INPUT_CHANNELS, OUTPUT_CHANNELS
from diamond_sss.diffusion.repair.inputs import RepairInputs
from diamond_sss.errors import DamagedFileError, DataError
from diamond_sss.runs.folder import load_scene
from diamond_sss.utils.io import atomic_save_safetensors, load_safetensors, read_json, sha256_file


def target_image(dataset: OLATDataset, index: int) -> Tensor:
    """Observation ``index`` of ``dataset`` as the model's target: premultiplied sRGB and alpha ``[4, H, W]``."""
    sample = dataset.load(index)
    return torch.cat([linear_to_srgb(sample.rgb.clamp(0, 1)), sample.mask], dim=-1).permute(2, 0, 1).float()


def unseen_observations(dataset: OLATDataset, seen: Sequence[int], most: int, seed: int) -> list[int]:
    """At most ``most`` observations of ``dataset`` outside ``seen`` (0: all), a seeded draw, in index order."""
    unseen = sorted(set(range(len(dataset.observations))) - set(seen))
    if 0 < most < len(unseen):
        chosen = torch.randperm(len(unseen), generator=torch.Generator().manual_seed(seed))[:most]
        unseen = sorted(unseen[int(i)] for i in chosen)
    return unseen


def check_same_rig(capture: OLATDataset, twin: OLATDataset, tolerance: float = 1e-4) -> None:
    """Raise :class:`DataError` unless ``twin`` has ``capture``'s views and lights, in the same order: camera centres
    and light positions within ``tolerance`` of the capture's camera distance (intrinsics may differ)."""
    where = f"{twin.json_path} (the lattice twin of {capture.json_path})"
    if (twin.num_views, twin.num_lights) != (capture.num_views, capture.num_lights):
        raise DataError(f"{where}: {twin.num_views} views and {twin.num_lights} lights, the capture has "
                        f"{capture.num_views} and {capture.num_lights}; render the twin with the capture's rig and seed")
    scale = float(capture.camera_centers.norm(dim=-1).max())
    for name, ours, theirs in (("camera centre", twin.camera_centers, capture.camera_centers),
                               ("light position", twin.light_positions, capture.light_positions)):
        offset = (ours - theirs).norm(dim=-1)
        worst = int(torch.argmax(offset))
        if float(offset[worst]) > tolerance * scale:
            raise DataError(f"{where}: {name} {worst} is {float(offset[worst]):.4g} away from the capture's; the twin "
                            "must keep the capture's cameras and lights and change only the intrinsics")


def write_pairs(run: Path, out: Path, *, data: Path | None = None, lattice: Path | None = None,
                split: str = "train", most: int = 200, seed: int = 0, show_progress: bool = True) -> Path:
    """Pairs of the reconstruction in ``run`` (a finished ``train`` run folder; ``regime.json`` names the images it
    saw) on the capture ``data`` (default: the one its ``data.json`` names), written to ``out``: at the capture's
    images it did not see, or at those of ``lattice`` (the same split of a twin capture, :func:`check_same_rig`)
    whose view and light it did not see."""
    run = Path(run)
    regime_file, data_file = run / "regime.json", run / "data.json"
    if not regime_file.is_file():
        raise DataError(f"{run}: no regime.json; give a finished `diamond-sss train` run folder")
    if data is None:
        recorded = read_json(data_file) if data_file.is_file() else {}
        if not isinstance(recorded, dict) or "data" not in recorded:
            raise DataError(f"{data_file}: no 'data' key naming the capture; give it with --data")
        data = Path(recorded["data"])
    scene, cfg = load_scene(run)
    dataset = OLATDataset(data, split, downscale=cfg.runtime.downscale)
    recorded_regime = read_json(regime_file)
    if not (isinstance(recorded_regime, dict) and isinstance(recorded_regime.get("observations"), list)):
        raise DataError(f"{regime_file}: no 'observations' list (the images the run saw); is it a `diamond-sss "
                        "train` run folder?")
    seen = [int(i) for i in recorded_regime["observations"]]
    if max(seen, default=-1) >= len(dataset.observations):
        raise DataError(f"{regime_file}: observation {max(seen)} is not in {dataset.json_path} "
                        f"({len(dataset.observations)} images): the run was trained on another capture")
    targets_of = dataset
    if lattice is not None:
        targets_of = OLATDataset(lattice, split, downscale=cfg.runtime.downscale)
        check_same_rig(dataset, targets_of)
    seen_pairs = {(dataset.observations[i].view, dataset.observations[i].light) for i in seen}
    seen_there = [i for i, obs in enumerate(targets_of.observations) if (obs.view, obs.light) in seen_pairs]
    builder = RepairInputs(scene.eval(), targets_of, dataset, seen)
    inputs, targets = [], []
    for index in tqdm(unseen_observations(targets_of, seen_there, most, seed), desc=f"repair pairs {run.name}",
                      unit="pair", disable=not show_progress, dynamic_ncols=True):
        obs = targets_of.observations[index]
        inputs.append(builder.target(obs.view, obs.light)[0].half())
        targets.append(target_image(targets_of, index).half())
    if not inputs:
        raise DataError(f"{run}: the reconstruction saw every image of {targets_of.json_path}: no pair to make")
    metadata = {"run": str(run.resolve()), "data": str(Path(data).resolve()),
                "lattice": str(targets_of.root), "model_sha256": sha256_file(run / "model.safetensors"),
                "pairs": str(len(inputs))}
    return atomic_save_safetensors(out, {"inputs": torch.stack(inputs), "targets": torch.stack(targets)},
                                   metadata=metadata)


def read_pair_metadata(path: str | os.PathLike) -> dict[str, str]:
    """The metadata :func:`write_pairs` recorded in ``path``."""
    if not Path(path).is_file():
        raise DataError(f"{path}: pair file is missing")
    try:
        with safe_open(str(path), framework="pt") as handle:
            return dict(handle.metadata() or {})
    except (SafetensorError, OSError) as exc:
        raise DamagedFileError(f"{path}: damaged or truncated pair file ({exc})") from exc


@dataclass
class RepairPairs:
    """Pairs of one or more files, concatenated: ``inputs [N, 23, H, W]``, ``targets [N, 4, H, W]`` (float32)."""

    inputs: Tensor
    targets: Tensor
    files: list[str]

    @classmethod
    def read(cls, paths: Sequence[str | os.PathLike]) -> RepairPairs:
        """The pairs of ``paths`` (same image size in all)."""
        if not paths:
            raise DataError("repair pairs: no pair file given")
        inputs, targets = [], []
        for path in paths:
            tensors = load_safetensors(path)
            if set(tensors) != {"inputs", "targets"}:
                raise DataError(f"{path}: not a repair pair file (keys {sorted(tensors)}, expected inputs, targets)")
            inputs.append(tensors["inputs"].float())
            targets.append(tensors["targets"].float())
            if inputs[-1].shape[1] != INPUT_CHANNELS or targets[-1].shape[1] != OUTPUT_CHANNELS:
                raise DataError(f"{path}: inputs of {inputs[-1].shape[1]} and targets of {targets[-1].shape[1]} "
                                f"channels, expected {INPUT_CHANNELS} and {OUTPUT_CHANNELS}")
            if not (torch.isfinite(inputs[-1]).all() and torch.isfinite(targets[-1]).all()):
                raise DataError(f"{path}: holds a non-finite value (NaN or inf); write it again with repair-data")
            if inputs[-1].shape[-2:] != inputs[0].shape[-2:]:
                raise DataError(f"{path}: {tuple(inputs[-1].shape[-2:])} images, the first file's are "
                                f"{tuple(inputs[0].shape[-2:])}")
        return cls(torch.cat(inputs), torch.cat(targets), [str(p) for p in paths])

    def __len__(self) -> int:
        return self.inputs.shape[0]

    def batch(self, count: int, crop: int, generator: torch.Generator,
              zoom_out: float = 1.0) -> tuple[Tensor, Tensor]:
        """``count`` random pairs (with replacement), each shrunk by a random factor in ``[zoom_out, 1]``
        (:func:`shrunk_pair`) when ``zoom_out`` < 1, then a random ``crop`` x ``crop`` window (0: whole)."""
        index = torch.randint(0, len(self), (count,), generator=generator)
        inputs, targets = self.inputs[index], self.targets[index]
        if zoom_out < 1.0:
            factors = zoom_out + (1.0 - zoom_out) * torch.rand(count, generator=generator)
            shrunk = [shrunk_pair(inputs[i], targets[i], float(factors[i]), generator) for i in range(count)]
            inputs, targets = torch.stack([pair[0] for pair in shrunk]), torch.stack([pair[1] for pair in shrunk])
        height, width = inputs.shape[-2:]
        if crop <= 0 or crop >= min(height, width):
            return inputs, targets
        top = torch.randint(0, height - crop + 1, (count,), generator=generator)
        left = torch.randint(0, width - crop + 1, (count,), generator=generator)
        rows = top[:, None] + torch.arange(crop)
        cols = left[:, None] + torch.arange(crop)
        pick = torch.arange(count)[:, None, None]

        def window(x: Tensor) -> Tensor:
            return x.permute(0, 2, 3, 1)[pick, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2)

        return window(inputs), window(targets)


def shrunk_pair(inputs: Tensor, targets: Tensor, factor: float, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """One pair (``[23, H, W]``, ``[4, H, W]``) as a rig framing the object ``factor`` times as large would see it:
    every image channel area-resampled to ``round(factor H) x round(factor W)`` and put at a random place in an
    empty (zero) image of the same size; the light code, constant over the image, is kept."""
    height, width = inputs.shape[-2:]
    small = (max(1, round(factor * height)), max(1, round(factor * width)))
    top = int(torch.randint(0, height - small[0] + 1, (), generator=generator))
    left = int(torch.randint(0, width - small[1] + 1, (), generator=generator))

    def placed(images: Tensor) -> Tensor:
        canvas = torch.zeros_like(images)
        canvas[:, top:top + small[0], left:left + small[1]] = F.interpolate(images[None], size=small, mode="area")[0]
        return canvas

    return torch.cat([placed(inputs[:IMAGE_CHANNELS]), inputs[IMAGE_CHANNELS:]]), placed(targets)

