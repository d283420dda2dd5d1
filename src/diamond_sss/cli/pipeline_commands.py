"""``diamond-sss run``: the DIAMOND-SSS pipeline, from a sparse OLAT capture to an evaluated reconstruction."""

from __future__ import annotations

import json as json_module
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console

from diamond_sss.cli.options import PresetArg, SetArg, config_from, options_of, schedule_overrides
from diamond_sss.pipeline.config import SHORT_RUN_PRELIM_PRESET, PipelineConfig

PipelineOptions = options_of(PipelineConfig, exclude=("augment",))
"""Every :class:`PipelineConfig` field but ``augment`` (given as text: ``--augment auto``), as ``--flag``."""


def run(data: Path, out: Path, split: str = "train", regime: str = "views=5%,lights=5%", preset: PresetArg = "auto",
        augment: str = "auto", iterations: int | None = None, keep_schedule: bool = False, short_run: bool = False,
        set_: SetArg = [], seed: int = 0,  # noqa: B006
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
        augment: auto (repair when its model ships with the package, else the paper's stages whose model ships; it
            says why) | none | nvs | relight | nvs,relight | repair (beyond the paper: the renders repaired,
            docs/pipeline.md).
        iterations: training steps of each reconstruction (default: 1000 under --preset auto, the preset's
            otherwise); the short-run settings' or the named preset's step-valued keys are scaled by iterations /
            their iterations, as `diamond-sss train --iterations` does.
        keep_schedule: with --iterations and a named --preset, keep the preset's step-valued keys as they are.
        short_run: kept for old scripts, the default preset auto runs with these settings: the settings measured for
            runs of 1,000 to 10,000 steps on 64-px captures, with which the demo and benchmarks/regimes.py run the
            pipeline (training.config.short_schedule), scaled to --iterations (default 1000): the final
            reconstruction (diamond under --preset auto, else the named preset) with PIPELINE_FINAL_RUN, the
            preliminary one as theirs, the sss3dgs preset (unless --prelim-preset) with Eq. A.1's L1; --set's keys
            come after them. A named --preset without --short-run trains both reconstructions with that preset
            (the preliminary one with --prelim-preset if given). The benchmarks reuse their `diamond-sss train
            --preset sss3dgs --short-run` run of the same regime and seed (the SSS-3DGS row) as the preliminary
            one: give it as --prelim-run to do the same.
        seed: seed of the regime, reconstructions and diffusion noise.
        json: print the final metrics as JSON.
        quiet: no progress bars.
        pipeline: the pipeline's settings (PipelineConfig).
    """
    from diamond_sss.pipeline.run import (
        AUTO_AUGMENT_WHY,
        auto_framing,
        parse_augment,
        run_pipeline,
    )
    from diamond_sss.training.config import AUTO_PRESET
    from diamond_sss.training.overrides import parse_sets

    short = short_run or preset == AUTO_PRESET
    sets = parse_sets(set_)
    preset, schedule, said = schedule_overrides(preset, iterations, keep_schedule=keep_schedule, short_run=short_run,
                                                pipeline_final=True, fixed=sets)
    overrides = {**schedule, **sets}
    cfg = config_from(PipelineConfig, pipeline, augment=parse_augment(augment))
    prelim_overrides = None
    if short:
        prelim_preset, prelim_schedule, _ = schedule_overrides(cfg.prelim_preset or SHORT_RUN_PRELIM_PRESET,
                                                               iterations, short_run=True)
        cfg = replace(cfg, prelim_preset=prelim_preset)
        prelim_overrides = {**prelim_schedule, **sets}
        final_only = ", ".join(f"{key}={schedule[key]}" for key in schedule if key not in prelim_schedule)
        prelim_only = ", ".join(f"{key}={value}" for key, value in prelim_schedule.items()
                                if key not in schedule or schedule[key] != value)
        said = (f"final reconstruction ({preset}): {said}\npreliminary reconstruction ({cfg.prelim_preset}): the same "
                f"settings" + (f" without {final_only}" if final_only else "")
                + (f"; with a sparse capture's {prelim_only} (on the real images alone)" if prelim_only else "")
                + (" (not trained: --prelim-run gives it)" if cfg.prelim_run else ""))
    if augment.strip() == "auto":
        said = "\n".join(filter(None, [said, f"--augment auto -> {','.join(cfg.augment) or 'none'}: {AUTO_AUGMENT_WHY}"]))
    if cfg.rig_framing == "auto" and cfg.augment:
        said = "\n".join(filter(None, [said, "--rig-framing auto -> {}: {}".format(*auto_framing(cfg))]))
    if said:
        Console(soft_wrap=True).print(said)
    result = run_pipeline(data, out, split=split, regime=regime, preset=preset, overrides=overrides,
                          prelim_overrides=prelim_overrides, seed=seed, config=cfg, show_progress=not quiet)
    if json:
        print(json_module.dumps(result, indent=2))
    else:
        Console().print(result)
