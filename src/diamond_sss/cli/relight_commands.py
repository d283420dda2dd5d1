"""``diamond-sss finetune-relight | relight``: train the relighting diffusion model and relight a view."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console

from diamond_sss.cli.options import config_from, options_of
from diamond_sss.diffusion.relight.config import RelightAugmentConfig, RelightModelConfig, RelightTrainConfig

RelightTrainOptions = options_of(RelightTrainConfig, exclude=("losses", "augment"))
RelightModelOptions = options_of(RelightModelConfig, include=("resolution", "use_source_light", "shading_hint"))


def finetune_relight(
    out: Path,
    pretrained_sd: Path | None = None,
    init: Path | None = None,
    data: list[Path] | None = None,
    augment: bool = True,
    lpips_weights: str | None = None,
    resume: bool = True,
    quiet: bool = False,
    training: Annotated[RelightTrainOptions, tyro.conf.OmitArgPrefixes] = RelightTrainOptions(),  # noqa: B008
    model: Annotated[RelightModelOptions, tyro.conf.OmitArgPrefixes] = RelightModelOptions(),  # noqa: B008
) -> None:
    """Fine-tune the relighting diffusion model on the embedded fine-tuning objects (view fixed, <= 7%).

    Writes <out>/model (config.json + model.safetensors, the EMA weights), <out>/checkpoints/step_*,
    <out>/train_log.jsonl, <out>/selection.json (the images used) and <out>/finetune_config.json.

    Args:
        out: run folder.
        pretrained_sd: local Stable Diffusion folder (diffusers format): latent-space model (paper's route).
        init: start from the weights of a relighting model folder (config.json + model.safetensors).
        data: data folders to use instead of the embedded fine-tuning objects.
        augment: mirror the pairs, vary their exposure and tint, permute their colours (exact symmetries of light
            transport).
        lpips_weights: LPIPS (VGG) weights in safetensors; the LPIPS term is skipped without them.
        resume: continue from the newest checkpoint in <out>/checkpoints.
        quiet: no log lines.
        training: fine-tuning settings (RelightTrainConfig).
        model: the model's settings (RelightModelConfig; the shading hint also makes the model denoise the
            residual from it).
    """
    from diamond_sss.diffusion.relight.data import load_finetune_views, load_relight_views
    from diamond_sss.diffusion.relight.model import RelightDiffusion
    from diamond_sss.diffusion.relight.train import finetune
    from diamond_sss.losses.lpips import load_lpips

    model_config = config_from(RelightModelConfig, model, residual=model.shading_hint)
    seed = training.seed
    if init is not None:
        relight_model = RelightDiffusion.load(init)
    elif pretrained_sd is not None:
        relight_model = RelightDiffusion.from_pretrained_sd(pretrained_sd, model_config, seed=seed)
    else:
        relight_model = RelightDiffusion.from_config(model_config, seed=seed)
    views = (
        load_relight_views(list(data), relight_model.config.resolution)
        if data
        else load_finetune_views(relight_model.config.resolution)
    )
    config = config_from(RelightTrainConfig, training,
                         augment=RelightAugmentConfig() if augment else RelightAugmentConfig.off())
    console = Console()
    lpips = load_lpips(lpips_weights)

    folder = finetune(views, out, relight_model, config, lpips=lpips, resume=resume,
                      log=(lambda _: None) if quiet else console.print)
    console.print(f"relighting model -> {folder}")


def relight(
    data: Path,
    view: int,
    source_light: int,
    target_lights: str,
    geometry: str,
    out: Path,
    split: str = "train",
    model: Path | None = None,
    steps: int = 1,
    samples: int = 8,
    seed: int = 0,
    cache: Path | None = None,
    device: str = "auto",
) -> None:
    """Relight one view of a capture from its source light to target lights with the diffusion model.

    Writes <out>/images/v<view>_l<light>.png (RGBA, premultiplied over black), <out>/masks/ and
    <out>/manifest.json ([{view, light, image, mask}] with lattice indices, paths relative to <out>).
    Results are cached on disk keyed by the model hash and the input hash.

    Args:
        data: data folder holding transforms_<split>.json.
        view: view index in the split's camera lattice.
        source_light: light index of the source image.
        target_lights: light indices to generate, comma separated (e.g. 3,5,7).
        geometry: a reconstruction run folder, 'maps', 'depth-anything:PATH', 'marigold:PATH' or
            'depth-anything:PATH+marigold:PATH'.
        out: output folder.
        split: data split.
        model: relighting model folder (default: the one shipped in the package).
        steps: DDIM steps (the shipped model is best with 1: see benchmarks/RESULTS.md).
        samples: samples averaged per image (test-time ensemble).
        seed: noise seed.
        cache: cache folder (default $DIAMOND_SSS_CACHE/relight or ~/.cache/diamond_sss/relight).
        device: auto (CUDA when available, else CPU) | cpu | cuda[:i].
    """
    from diamond_sss.data.dataset import OLATDataset
    from diamond_sss.diffusion.common.cache import OutputCache
    from diamond_sss.diffusion.geometry import geometry_source
    from diamond_sss.diffusion.relight.inference import (
        default_cache_root,
        load_model,
        relight_view,
        write_relit,
    )
    from diamond_sss.utils.device import resolve_device

    try:
        lights = [int(x) for x in target_lights.split(",") if x.strip()]
    except ValueError as error:
        raise ValueError(
            f"--target-lights must be comma-separated light indices, got {target_lights!r}"
        ) from error
    if not lights:
        raise ValueError("no target lights given (--target-lights 3,5,7)")
    device = str(resolve_device(device))
    source = geometry_source(geometry, device=device, seed=seed)
    relit = relight_view(
        load_model(model, device),
        OLATDataset(data, split),
        view,
        source_light,
        lights,
        source,
        OutputCache(cache or default_cache_root()),
        num_steps=steps,
        seed=seed,
        samples=samples,
    )
    manifest = write_relit(out, relit)
    hits = sum(item.cached for item in relit)
    Console().print(f"relit view {view} to {len(relit)} lights ({hits} from cache) -> {manifest}")
