"""Relight one view of a capture to several target lights, with an on-disk cache and a manifest.

Cache key of one relit image: the model's weight hash, the source image's and its mask's file hashes, the camera,
the geometry source's identity (with the content of the maps it reads), the source and target lights, the DDIM steps, the number of samples and the
seed. The initial noise of sample ``k`` of target light ``l`` is drawn from ``seed``, ``l`` and ``k`` alone, so
a result does not depend on how the target lights were batched. With ``samples > 1`` the image is the mean of
that many samples (a test-time ensemble, as in Marigold: it averages out the noise the sampler leaves).
The model sees the source area-downsampled to its resolution ``R``; a relit image is written at ``R`` (or at the
source's side where that is smaller: :func:`output_size`), its mask the source's area-resized to that size.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.images import load_rgba, resize_area, to_srgb8, write_png
from diamond_sss.diffusion.common.cache import OutputCache
from diamond_sss.diffusion.common.manifest import GeneratedImage, image_paths, write_image_manifest
from diamond_sss.diffusion.common.model_io import CONFIG_NAME, WEIGHTS_NAME
from diamond_sss.diffusion.common.paths import default_cache_dir, shipped_model_dir
from diamond_sss.diffusion.geometry.base import GeometrySource
from diamond_sss.diffusion.relight.conditioning import conditioning_image
from diamond_sss.diffusion.relight.light import light_code
from diamond_sss.diffusion.relight.model import RelightDiffusion
from diamond_sss.diffusion.relight.pipeline import RelightPipeline
from diamond_sss.utils.io import sha256_file


@dataclass
class RelitImage:
    """One generated image: linear premultiplied ``rgb [H,W,3]``, ``mask [H,W,1]``, cache folder and hit."""

    view: int
    light: int
    rgb: Tensor
    mask: Tensor
    entry: Path
    cached: bool


def shipped_model_path() -> Path:
    """The relighting model shipped in the package (:func:`~diamond_sss.diffusion.common.paths.shipped_model_dir`)."""
    return shipped_model_dir("relight")


def default_cache_root() -> Path:
    """The relighting cache (:func:`~diamond_sss.diffusion.common.paths.default_cache_dir`)."""
    return default_cache_dir("relight")


def load_model(path: str | os.PathLike | None = None, device: str = "cpu") -> RelightDiffusion:
    """The model in ``path`` (default: the shipped one); a clear error when it is missing."""
    folder = Path(path) if path is not None else shipped_model_path()
    if not (folder / CONFIG_NAME).is_file() or not (folder / WEIGHTS_NAME).is_file():
        hint = "" if path is not None else " (no trained relighting model is shipped; pass --model)"
        raise FileNotFoundError(
            f"relighting model not found: {folder} needs {CONFIG_NAME} and {WEIGHTS_NAME}{hint}"
        )
    return RelightDiffusion.load(folder).to(device)


def output_size(height: int, width: int, resolution: int) -> tuple[int, int]:
    """``(min(height, R), min(width, R))``: the size of a relit image of an ``height x width`` source by a model of
    resolution ``R`` (never upsampled past what the model made)."""
    return min(height, resolution), min(width, resolution)


def relight_view(
    model: RelightDiffusion,
    dataset: OLATDataset,
    view: int,
    source_light: int,
    target_lights: list[int],
    geometry: GeometrySource,
    cache: OutputCache,
    num_steps: int = 1,
    seed: int = 0,
    samples: int = 8,
) -> list[RelitImage]:
    """Relight ``(view, source_light)`` of ``dataset`` to every light in ``target_lights`` (lattice indices).

    Cache misses are generated in one batch per sample; hits are read back. Raises ``ValueError`` naming the view or
    light when the source image or a target light does not exist.
    """
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    if not 0 <= view < dataset.num_views:
        raise ValueError(f"view {view} out of range: {dataset.json_path} has {dataset.num_views} views")
    for light in [source_light, *target_lights]:
        if not 0 <= light < dataset.num_lights:
            raise ValueError(
                f"light {light} out of range: {dataset.json_path} has {dataset.num_lights} lights"
            )
    try:
        index = dataset.observation_index(view, source_light)
    except KeyError as error:
        raise ValueError(
            f"no source image of view {view} under light {source_light} in {dataset.json_path}"
        ) from error
    sample = dataset.load(index)
    bounds = dataset.bounds
    w2c = dataset.viewmats[view]
    observation = dataset.observations[index]
    codes = light_code(
        dataset.light_positions, w2c.expand(dataset.num_lights, 4, 4), bounds.center, bounds.radius
    )
    source_key = {
        "model": model.weights_hash(),
        "image": sha256_file(observation.image_path),
        "mask": None if observation.mask_path is None else sha256_file(observation.mask_path),
        "w2c": w2c.flatten().tolist(),
        "K": dataset.intrinsics[view].flatten().tolist(),
        "geometry": geometry.view_key(dataset, view),
        "source_code": codes[source_light].tolist(),
        "steps": num_steps,
        "samples": samples,
        "seed": seed,
        "size": output_size(*sample.rgb.shape[:2], model.config.resolution),
    }
    keys = {
        light: cache.key({**source_key, "target_code": codes[light].tolist(), "light": light})
        for light in target_lights
    }
    misses = sorted({light for light in target_lights if cache.get(keys[light]) is None})
    if misses:
        _generate(
            model,
            dataset,
            view,
            sample.rgb,
            sample.mask,
            misses,
            codes,
            source_light,
            geometry,
            cache,
            keys,
            num_steps,
            seed,
            samples,
        )
    results = []
    for light in target_lights:
        entry = cache.get(keys[light])
        rgb, mask = load_rgba(entry / "image.png", premultiplied=True)
        results.append(
            RelitImage(view=view, light=light, rgb=rgb, mask=mask, entry=entry, cached=light not in misses)
        )
    return results


def _generate(
    model: RelightDiffusion,
    dataset: OLATDataset,
    view: int,
    rgb: Tensor,
    mask: Tensor,
    lights: list[int],
    codes: Tensor,
    source_light: int,
    geometry: GeometrySource,
    cache: OutputCache,
    keys: dict[int, str],
    num_steps: int,
    seed: int,
    samples: int,
) -> None:
    maps = geometry.maps(dataset, view, rgb, mask)
    device = next(model.parameters()).device
    count = len(lights)
    try:
        single = conditioning_image(
            rgb[None], maps.nearness[None], maps.normals[None], mask[None], model.config.resolution
        )
    except ValueError as error:
        raise ValueError(
            f"view {view} of {dataset.json_path} (geometry {geometry.key()}): {error}"
        ) from error
    cond = single.expand(count, -1, -1, -1).to(device)
    shape = model.sample_shape(1)[1:]
    target_codes = codes[lights].to(device)
    source_codes = codes[[source_light] * count].to(device)
    with torch.no_grad():
        fit = model.scattering_fit(single.to(device), source_codes[:1])
        hint = model.hint(cond, target_codes, source_codes, fit=None if fit is None else fit.expand(count))
    noise = torch.stack([
        torch.stack([
            torch.randn(shape, generator=torch.Generator().manual_seed(seed * 100_003 + light + sample * 1_000_003))
            for light in lights
        ])
        for sample in range(samples)
    ])
    size = output_size(*rgb.shape[:2], model.config.resolution)
    output = RelightPipeline(model)(cond, target_codes, source_codes, num_steps, noise=noise, hint=hint,
                                    samples=samples, size=size)
    mask = resize_area(mask, *size)
    images = output.rgb * (mask > 1e-3)
    for light, image in zip(lights, images):
        cache.put(
            keys[light], lambda folder, image=image: write_png(folder / "image.png", to_srgb8(image, mask))
        )


def write_relit(out: str | os.PathLike, results: list[RelitImage]) -> Path:
    """Write the images as ``v<view>_l<light>`` with ``manifest.json`` into ``out``
    (:mod:`~diamond_sss.diffusion.common.manifest`); returns the manifest path."""
    items = []
    for item in results:
        written = GeneratedImage(item.view, item.light, *image_paths(out, f"v{item.view:03d}_l{item.light:03d}"))
        write_png(written.image, to_srgb8(item.rgb, item.mask))
        write_png(written.mask, (item.mask[..., 0].numpy() * 255.0 + 0.5).astype("uint8"))
        items.append(written)
    return write_image_manifest(out, items)
