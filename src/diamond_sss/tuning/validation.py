"""The validation split of a study: images held out of the selected TRAINING images (never the test split).

A study scores a trial on what the regime gives it: the regime's training observations are split into
those the trial trains on and ``count`` held-out ones. Held-out observations are drawn (seeded) so that
their view and their light each stay seen in the remaining training images whenever the selection allows
it, so the validation PSNR measures interpolation between training views and lights rather than
extrapolation to an unseen camera.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.regimes import select_regime
from diamond_sss.evaluation.evaluate import render_observation
from diamond_sss.evaluation.metrics import psnr
from diamond_sss.scene.model import RelightableScene


def default_validation_count(images: int) -> int:
    """About 10% of the selected images, between 1 and 8."""
    return min(8, max(1, images // 10))


def holdout_positions(pairs: Sequence[tuple[int, int]], count: int, seed: int) -> list[int]:
    """Positions of ``count`` (view, light) ``pairs`` to hold out, sorted.

    Candidates are visited in a seeded random order; one is taken when its view and its light both keep
    at least one other training image. If fewer than ``count`` qualify, the rest are taken in the same
    order from the others. At least one image always stays for training.
    """
    if count < 1:
        raise ValueError(f"the validation split needs at least 1 image, got {count}")
    if count >= len(pairs):
        raise ValueError(f"cannot hold out {count} of {len(pairs)} selected images: at least one must train")
    order = torch.randperm(len(pairs), generator=torch.Generator().manual_seed(seed)).tolist()
    views = Counter(view for view, _ in pairs)
    lights = Counter(light for _, light in pairs)
    chosen: list[int] = []
    for position in order:
        view, light = pairs[position]
        if len(chosen) < count and views[view] > 1 and lights[light] > 1:
            chosen.append(position)
            views[view] -= 1
            lights[light] -= 1
    remaining = [position for position in order if position not in chosen]
    chosen.extend(remaining[: count - len(chosen)])
    return sorted(chosen)


@dataclass
class TuneData:
    """The training images and the held-out validation images of a study (one shared lattice)."""

    train: OLATDataset
    validation: OLATDataset
    regime: str
    seed: int

    def describe(self) -> dict:
        """Views, lights and counts of both parts (what the study records)."""
        def pairs(ds: OLATDataset) -> list[list[int]]:
            return [[o.view, o.light] for o in ds.observations]
        return {"regime": self.regime, "seed": self.seed, "train_images": len(self.train),
                "validation_images": len(self.validation), "validation": pairs(self.validation)}


def load_tune_data(data: Path, *, split: str = "train", regime: str = "all", seed: int = 0,
                   validation_images: int | None = None, downscale: float = 1.0) -> TuneData:
    """Select the regime's images of ``split``; hold out the validation images (:func:`holdout_positions`)."""
    if split == "test":
        raise ValueError("a study never looks at the test split: tune on the training split")
    dataset = OLATDataset(data, split, downscale=downscale)
    selection = select_regime(dataset, regime, seed)
    observations = list(selection.observations)
    pairs = [(dataset.observations[i].view, dataset.observations[i].light) for i in observations]
    count = default_validation_count(len(pairs)) if validation_images is None else validation_images
    held = set(holdout_positions(pairs, count, seed))
    train = [obs for position, obs in enumerate(observations) if position not in held]
    validation = [obs for position, obs in enumerate(observations) if position in held]
    return TuneData(train=dataset.subset(train), validation=dataset.subset(validation), regime=regime,
                    seed=seed)


@torch.no_grad()
def validation_psnr(scene: RelightableScene, dataset: OLATDataset) -> float:
    """Mean PSNR (dB, sRGB in [0,1], full frame, black background) of ``scene`` over ``dataset``'s images.

    NaN when a render is not finite (a diverged trial).
    """
    device = next(scene.parameters()).device
    values = []
    for index in range(len(dataset)):
        render = render_observation(scene, dataset, index, device)
        radiance = render.radiance[0].float().cpu()
        if not bool(torch.isfinite(radiance).all()):
            return math.nan
        target = linear_to_srgb(dataset.load(index).rgb.float())
        values.append(psnr(linear_to_srgb(radiance), target))
    return sum(values) / len(values)
