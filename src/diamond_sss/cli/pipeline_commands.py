"""``diamond-sss run``: the DIAMOND-SSS pipeline, from a sparse OLAT capture to an evaluated reconstruction."""

from __future__ import annotations

import json as json_module
from pathlib import Path

from rich.console import Console

from diamond_sss.cli.options import SetArg


def run(data: Path, out: Path, split: str = "train", regime: str = "views=5%,lights=5%", preset: str = "diamond",
        augment: str = "auto", iterations: int | None = None, set_: SetArg = [],  # noqa: B006
        nvs_views: int = 12, relight_lights: int = 8, nvs_model: str | None = None,
        relight_model: str | None = None, nvs_steps: int = 1, relight_steps: int = 1,
        relight_samples: int = 8, cache_dir: str | None = None, seed: int = 0,
        device: str = "cpu", json: bool = False, quiet: bool = False) -> None:
    """Diffusion-augmented sparse reconstruction (supplement Sec. C.4): prelim -> nvs -> relight -> final -> eval.

    Every stage is cached and resumable (rerun the same command after a kill); pipeline.json records inputs,
    seeds, model hashes, counts of real and synthetic images and time per stage.

    Args:
        data: data folder (transforms_<split>.json; transforms_test.json for the evaluation).
        out: pipeline folder.
        split: training split.
        regime: capture regime of the real images (e.g. views=5%,lights=5%).
        preset: reconstruction preset for the preliminary and final reconstructions.
        augment: auto (the stages whose model ships with the package) | none | nvs | relight | nvs,relight.
        iterations: training steps of each reconstruction (default: the preset's).
        nvs_views: at most this many missing views generated per real light (0: all).
        relight_lights: at most this many missing lights generated per view (0: all).
        nvs_model: folder of a novel-view model (default: the shipped one).
        relight_model: folder of a relighting model (default: the shipped one).
        nvs_steps: DDIM steps of the novel-view model (the shipped model is best with 1).
        relight_steps: DDIM steps of the relighting model (the shipped model is best with 1).
        relight_samples: relighting samples averaged per image (test-time ensemble).
        cache_dir: cache of generated images (default: ~/.cache/diamond_sss or $DIAMOND_SSS_CACHE).
        seed: seed of the regime, reconstructions and diffusion noise.
        device: cpu | cuda for the diffusion models (reconstructions use --set device=...).
        json: print the final metrics as JSON.
        quiet: no progress bars.
    """
    from diamond_sss.pipeline.run import PipelineConfig, parse_augment, run_pipeline
    from diamond_sss.training.overrides import parse_sets

    stages = parse_augment(augment)
    overrides = parse_sets(set_)
    if iterations is not None:
        overrides["iterations"] = iterations
    cfg = PipelineConfig(augment=stages, nvs_views=nvs_views, relight_lights=relight_lights, nvs_model=nvs_model,
                         relight_model=relight_model, nvs_steps=nvs_steps, relight_steps=relight_steps,
                         relight_samples=relight_samples, cache_dir=cache_dir,
                         device=device)
    result = run_pipeline(data, out, split=split, regime=regime, preset=preset, overrides=overrides, seed=seed,
                          config=cfg, show_progress=not quiet)
    if json:
        print(json_module.dumps(result, indent=2))
    else:
        Console().print(result)
