"""``diamond-sss train | eval | render | export``: reconstruct, score, render and export a scene."""

from __future__ import annotations

import json as json_module
import math
from pathlib import Path

from rich.console import Console
from rich.table import Table

from diamond_sss.cli.options import PresetArg, SetArg, given_overrides, schedule_overrides


def train(data: Path, out: Path, split: str = "train", regime: str = "all", preset: PresetArg = "auto",
          iterations: int | None = None, keep_schedule: bool = False, short_run: bool = False,
          config: Path | None = None,
          set_: SetArg = [], seed: int | None = None, resume: bool = False,  # noqa: B006
          device: str | None = None, quiet: bool = False) -> None:
    """Reconstruct a relightable translucent object from an OLAT data set (SSS-3DGS backbone).

    Args:
        data: data folder holding transforms_<split>.json.
        out: run folder (config, regime, checkpoints, TensorBoard logs, model.safetensors).
        split: training split.
        regime: capture regime: all | all-views-1-light | views=5%,lights=5% | views=5,lights=6 | images=10.
        iterations: training steps (default: 1000 under --preset auto, the preset's otherwise); the short-run
            settings' or the named preset's (and --config's) step-valued keys (densification start, stop and
            interval, opacity reset, learning rate schedule, checkpoint and log intervals) are scaled by
            iterations / their iterations.
        keep_schedule: with --iterations and a named --preset, keep the preset's step-valued keys as they are.
        short_run: kept for old scripts, the default preset auto trains with these settings: the settings measured
            for runs of 1,000 to 10,000 steps on 64-px captures (training.config.short_schedule; a dense capture's
            when the regime selects 100 images or more), scaled to --iterations (default 1000); with a named
            --preset, that preset with them; --config's keys and --set's come after them.
        config: JSON file of config keys (e.g. the best configuration written by `diamond-sss tune`).
        seed: seed of the regime selection, initialisation and every random draw (schedule.seed; default:
            --config's, else the preset's).
        resume: continue from the newest checkpoint in --out.
        device: auto | cpu | cuda (runtime.device; default: --config's, else the preset's).
        quiet: no progress bar.
    """
    from diamond_sss.training.config import AUTO_PRESET, DENSE_MIN_IMAGES, Schedule
    from diamond_sss.training.overrides import checked_values, config_file_values, make_config, parse_sets
    from diamond_sss.training.run import selected_images, train_run

    console = Console(soft_wrap=True)
    from_file = config_file_values(config) if config is not None else {}
    sets = checked_values(parse_sets(set_))
    flags = checked_values(given_overrides(seed=seed, device=device))
    images = selected_images(data, split, regime, {**from_file, **flags, **sets}.get("schedule.seed", Schedule.seed))
    short = short_run or preset == AUTO_PRESET
    preset, schedule, said = schedule_overrides(preset, iterations, keep_schedule=keep_schedule, short_run=short_run,
                                                dense=images >= DENSE_MIN_IMAGES, given=from_file, fixed=sets)
    if said and short:
        said += (f" ({'a dense' if images >= DENSE_MIN_IMAGES else 'a sparse'} capture's: regime {regime} selects "
                 f"{images} images, dense from {DENSE_MIN_IMAGES})")
    resolved = make_config(preset, overrides={**from_file, **schedule, **flags, **sets})  # before anything is written
    if said:
        console.print(said)
    result = train_run(data, out, resolved, split=split, regime=regime, resume=resume, show_progress=not quiet)
    console.print(f"trained {result.steps} steps in {result.seconds:.1f} s, {result.num_gaussians} Gaussians, "
                  f"final loss {result.final_loss:.4f} -> {out / 'model.safetensors'}")


def config(preset: PresetArg = "auto", iterations: int | None = None, regime: str = "all", json: bool = False) -> None:
    """List every config key (for --set and --config) with the value `train` gives it and its meaning.

    Args:
        iterations: training steps, as `train --iterations` (default: 1000 under --preset auto, the preset's
            otherwise).
        regime: capture regime, as `train --regime` (under --preset auto, all is shown with a dense capture's
            settings; `train` decides by how many images its regime selects: 100 or more).
        json: print a JSON object of key -> value instead of a table.
    """
    from diamond_sss.training.overrides import describe_config

    resolved, overrides, _ = schedule_overrides(preset, iterations, dense=regime == "all")
    rows = describe_config(resolved, overrides)
    if json:
        print(json_module.dumps({key: value for key, _, value, _ in rows}, indent=2))
        return
    shown = f"'{preset}'" + (f" = {resolved} with the short-run settings for {overrides['schedule.iterations']} "
                              f"steps, regime {regime}" + (" (a dense capture's)" if regime == "all" else "")
                              if resolved != preset else "")
    table = Table(title=f"config keys, preset {shown} (change with --set key=value or --set flat_name=value)")
    table.add_column("key", no_wrap=True)
    table.add_column("value")
    table.add_column("meaning [flat name]")
    for key, flat, value, meaning in rows:
        table.add_row(key, str(value), f"{meaning} [{flat}]")
    Console(soft_wrap=True).print(table)


def evaluate(run: Path, data: Path, split: str = "test", json: bool = False, lpips_weights: str | None = None,
             max_images: int | None = None, figures: int = 4, device: str = "auto") -> None:
    """Score a trained run on a split (default: novel views under novel lights).

    Writes <run>/eval_<split>/metrics.json, per_image.csv, comparison.png and decomposition.png.
    Metrics on sRGB images in [0,1], full frame, black background.

    Args:
        run: training run folder.
        data: data folder holding transforms_<split>.json.
        split: evaluation split.
        json: print the metrics JSON instead of a table.
        lpips_weights: LPIPS (VGG) weights in safetensors; default $DIAMOND_SSS_LPIPS_WEIGHTS; none -> lpips null.
        max_images: evaluate only the first N images.
        figures: rows of the GT | render | error figure (0: no figures).
        device: auto | cpu | cuda.
    """
    from diamond_sss.evaluation.run import evaluate_run

    summary = evaluate_run(run, data, split=split, lpips_weights=lpips_weights, max_images=max_images,
                           figures=figures, device=device, show_progress=not json)
    if json:
        print(json_module.dumps(summary, indent=2))
        return
    table = Table(title=f"{run} on {data} [{split}]")
    for key in ("psnr", "ssim", "lpips", "masked_psnr", "mask_iou", "images"):
        table.add_column(key)
    table.add_row(*[_fmt(summary[k]) for k in ("psnr", "ssim", "lpips", "masked_psnr", "mask_iou", "images")])
    Console().print(table)


def _fmt(value) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.4f}"
    return str(value)


def render(run: Path, out: Path, data: Path | None = None, split: str = "test", views: list[int] = [],  # noqa: B006
           orbit: int = 0, orbit_elevation_deg: float = 20.0, light: list[float] = [],  # noqa: B006
           light_intensity: float = 1.0, base_color: list[float] = [], roughness: float | None = None,  # noqa: B006
           metallic: float | None = None, subsurface: float | None = None, size: int | None = None,
           video: Path = Path("orbit.gif"), device: str = "auto") -> None:
    """Render a trained scene from data cameras or an orbit, under any point light(s), with material edits.

    Args:
        run: training run folder.
        out: output folder for PNGs (and the orbit animation).
        data: data folder whose cameras (and lights) to use; default: the run's training data.
        split: split of --data whose cameras --views index.
        views: lattice view indices of --split to render (default: all).
        orbit: render an orbit of N frames around the object instead (and the --video animation).
        orbit_elevation_deg: elevation of the orbit.
        light: light position(s) x y z [x y z ...] (several lights are summed); default: each view's
            first light in the data (an orbit's: that of the data's first image), at the capture's intensity.
        light_intensity: RGB intensity (grey) of each light given by --light.
        base_color: override the base colour (r g b, linear) of every Gaussian.
        roughness: override the roughness.
        metallic: override the metalness.
        subsurface: override the subsurfaceness s.
        size: side of the square orbit frames, centred on the object (default: the data's width).
        video: orbit animation, a name in --out or a path: .mp4 writes an MP4 (needs imageio-ffmpeg, the
            `video` extra), .gif a GIF.
        device: auto | cpu | cuda.
    """
    from diamond_sss.evaluation.run import render_run

    overrides = {k: v for k, v in (("base_color", base_color or None), ("roughness", roughness),
                                   ("metallic", metallic), ("subsurface", subsurface)) if v is not None}
    written = render_run(run, out, data=data, split=split, views=views, orbit=orbit,
                         orbit_elevation_deg=orbit_elevation_deg, lights=light, light_intensity=light_intensity,
                         overrides=overrides, size=size, device=device, video=video)
    Console().print(f"wrote {len(written)} files to {out}")


def export(run: Path, ply: Path) -> None:
    """Export a trained scene as a PLY with every attribute plus the standard 3DGS fields.

    Args:
        run: training run folder.
        ply: output .ply path (opens in common 3DGS viewers; colour from the base colour).
    """
    from diamond_sss.gaussians.ply import export_ply
    from diamond_sss.runs.folder import load_scene

    scene, _ = load_scene(run)
    export_ply(scene.gaussians, ply)
    Console().print(f"{scene.gaussians.num_gaussians} Gaussians -> {ply}")


def view(run: Path, port: int = 8080, host: str = "127.0.0.1", resolution: int = 256, device: str = "auto") -> None:
    """Open a trained scene in the web viewer (viser): orbit it, move the light, show maps, edit materials.

    Args:
        run: training run folder.
        port: port of the web server (open the printed URL in a browser).
        host: interface to listen on (default loopback only; 0.0.0.0 exposes the viewer to the network).
        resolution: initial image height of the rendered frames (pixels; a slider changes it).
        device: auto | cpu | cuda.
    """
    from diamond_sss.viewer.server import serve

    serve(run, host=host, port=port, resolution=resolution, device=device)


def ablate(data: Path, out: Path, regimes: list[str] = ["all", "views=5,lights=6", "views=3,lights=3"],  # noqa: B006
           variants: list[str] = ["sss3dgs", "diamond-no-mv", "+silhouette", "+depth", "+both",  # noqa: B006
                         "+both-all-targets"],
           iterations: int = 400, set_: SetArg = [], seed: int | None = None,  # noqa: B006
           quiet: bool = False) -> None:
    """Ablate the multi-view silhouette and depth losses (supplement Tab. 2) over capture regimes.

    Trains every variant on every regime (resumable run folders under --out), scores each on the test split
    and writes ablation.json, ablation.md and ablation_grid.png.

    Args:
        data: data folder with train and test splits.
        out: output folder.
        regimes: capture regimes to compare.
        variants: sss3dgs | diamond-no-mv | +silhouette | +depth | +both | +both-all-targets (targets also
            among the views without an image) | sss3dgs+silhouette | sss3dgs+depth | sss3dgs+both (the terms on
            the sss3dgs preset).
        iterations: training steps per run, with the short-run settings (training.config.short_schedule) scaled
            to them and, on a regime that selects 100 images or more, a dense capture's (DENSE_SHORT_RUN), as
            benchmarks/ablation.py trains; --set's keys come after them.
        seed: seed of every run (schedule.seed; default: the preset's).
        quiet: no progress bars.
    """
    from diamond_sss.experiments.ablation import ablation_table, run_ablation
    from diamond_sss.training.config import DENSE_SHORT_RUN, short_schedule
    from diamond_sss.training.overrides import checked_values, parse_sets

    sets = checked_values({**given_overrides(seed=seed), **parse_sets(set_)})
    dense = {key: value for key, value in checked_values(DENSE_SHORT_RUN).items() if key not in sets}
    rows = run_ablation(data, out, variants=variants, regimes=regimes, iterations=iterations,
                        overrides={**checked_values(short_schedule(iterations)), **sets}, dense_overrides=dense,
                        show_progress=not quiet)
    Console().print(ablation_table(rows))
