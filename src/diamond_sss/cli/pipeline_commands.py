"""``diamond-sss run``: the DIAMOND-SSS pipeline, from a sparse OLAT capture to an evaluated reconstruction."""

from __future__ import annotations

import json as json_module
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console

from diamond_sss.cli.options import SetArg, config_from, options_of
from diamond_sss.pipeline.config import PipelineConfig

PipelineOptions = options_of(PipelineConfig, exclude=("augment",))
"""Every :class:`PipelineConfig` field but ``augment`` (given as text: ``--augment auto``), as ``--flag``."""


def run(data: Path, out: Path, split: str = "train", regime: str = "views=5%,lights=5%", preset: str = "diamond",
        augment: str = "auto", iterations: int | None = None, set_: SetArg = [], seed: int = 0,  # noqa: B006
        json: bool = False, quiet: bool = False,
        pipeline: Annotated[PipelineOptions, tyro.conf.OmitArgPrefixes] = PipelineOptions()) -> None:  # noqa: B008
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
        seed: seed of the regime, reconstructions and diffusion noise.
        json: print the final metrics as JSON.
        quiet: no progress bars.
        pipeline: the pipeline's settings (PipelineConfig).
    """
    from diamond_sss.pipeline.run import parse_augment, run_pipeline
    from diamond_sss.training.overrides import parse_sets

    overrides = parse_sets(set_)
    if iterations is not None:
        overrides["iterations"] = iterations
    cfg = config_from(PipelineConfig, pipeline, augment=parse_augment(augment))
    result = run_pipeline(data, out, split=split, regime=regime, preset=preset, overrides=overrides, seed=seed,
                          config=cfg, show_progress=not quiet)
    if json:
        print(json_module.dumps(result, indent=2))
    else:
        Console().print(result)
