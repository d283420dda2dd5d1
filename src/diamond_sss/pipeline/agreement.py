"""Per-image weights of generated images from their agreement with the preliminary reconstruction.

The preliminary reconstruction is fitted to the regime's real images only; a generated image that it cannot
explain at all (a hallucinated part, a wrong shadow, a shifted highlight) is more likely a diffusion failure
than new information. For generated image ``i`` at lattice view ``v`` and light ``l``:

    e_i = mean over the union of both masks of |srgb(I_i) - srgb(R(v, l))|      (sRGB units, [0, 1])
    a_i = min(1, (median_j e_j / e_i) ^ power)                                   (power >= 0; 0: every a_i = 1)

with ``R`` the preliminary reconstruction's render; the image's photometric weight is ``alpha a_i``. Images at
or under the median error keep ``alpha``; worse ones lose weight in proportion to how much worse they are.
"""

from __future__ import annotations

import statistics

import torch

from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.images import load_rgba, resize_area
from diamond_sss.diffusion.common.manifest import GeneratedImage
from diamond_sss.pipeline.capture import check_on_lattice
from diamond_sss.runs.folder import render_lattice_image
from diamond_sss.scene.model import RelightableScene


def agreement_factors(errors: list[float], power: float) -> list[float]:
    """``a_i = min(1, (median(e) / e_i) ^ power)`` for the errors ``e`` (>= 0); all 1 when ``power`` is 0."""
    if power < 0.0:
        raise ValueError(f"agreement power must be >= 0, got {power}")
    if power == 0.0 or not errors:
        return [1.0] * len(errors)
    median = statistics.median(errors)
    return [1.0 if error <= median else (median / error) ** power for error in errors]


def load_generated(item: GeneratedImage, lattice: OLATDataset,
                   smaller: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Linear RGB and mask of a generated image, checked against the size of its lattice view (``smaller``: at most
    that size, as a diffusion model's resolution on a larger capture)."""
    rgb, mask = load_rgba(item.image, item.mask, premultiplied=True)
    camera = lattice.cameras[item.view]
    height, width = rgb.shape[:2]
    larger = width > camera.width or height > camera.height
    if larger or (not smaller and (width, height) != (camera.width, camera.height)):
        raise ValueError(f"{item.image}: generated image is {width}x{height}, the lattice's view {item.view} is "
                         f"{camera.width}x{camera.height}{' (it may be smaller, not larger)' if smaller else ''}")
    return rgb, mask


def render_errors(scene: RelightableScene, lattice: OLATDataset, items: list[GeneratedImage]) -> list[float]:
    """``e_i`` of each generated image against ``scene`` rendered at its view and light of ``lattice`` (area-downsampled
    to the image's size)."""
    errors = []
    for item in check_on_lattice(items, lattice):
        rgb, mask = load_generated(item, lattice, smaller=True)
        render = render_lattice_image(scene, lattice, item.view, item.light)
        height, width = rgb.shape[:2]
        rendered = resize_area(render.radiance[0].cpu(), height, width)
        union = torch.maximum(mask, resize_area(render.gbuffer.alpha[0].cpu(), height, width)).clamp(0.0, 1.0)
        difference = (linear_to_srgb(rgb.clamp_min(0.0)) - linear_to_srgb(rendered.clamp_min(0.0))).abs()
        errors.append(float((difference * union).sum() / (3.0 * union.sum()).clamp_min(1.0)))
    return errors
