"""The noise ceiling of a rendered capture: the best PSNR any model can score against its noisy images.

Two renders ``a``, ``b`` of the same image with independent Monte Carlo noise of variance ``s^2`` differ by
``E|a - b|^2 = 2 s^2``, while a noise-free prediction differs from ``a`` by ``s^2``; hence

    PSNR_ceiling = PSNR(a, b) + 10 log10(2)    (about +3.01 dB),

with PSNR on sRGB, full frame, averaged over images as :mod:`.metrics` averages test scores.
"""

from __future__ import annotations

import math

import numpy as np

from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.evaluation.metrics import psnr

TWO_RENDERS_DB = 10.0 * math.log10(2.0)


def noise_ceiling(first: OLATDataset, second: OLATDataset) -> dict[str, float]:
    """``{"render_psnr": mean PSNR(a, b), "ceiling_psnr": that + 3.01 dB, "images": n}``.

    ``first`` and ``second`` must list the same observations (same views, lights and image sizes).
    """
    pairs_a = [(o.view, o.light) for o in first.observations]
    pairs_b = [(o.view, o.light) for o in second.observations]
    if pairs_a != pairs_b or (first.width, first.height) != (second.width, second.height):
        raise ValueError(f"{first.json_path} and {second.json_path} do not hold the same observations: "
                         "the noise ceiling needs two renders of the same images")
    scores = [psnr(linear_to_srgb(first.load(i).rgb), linear_to_srgb(second.load(i).rgb))
              for i in range(len(first))]
    render_psnr = float(np.mean(scores))
    return {"render_psnr": render_psnr, "ceiling_psnr": render_psnr + TWO_RENDERS_DB, "images": len(scores)}
