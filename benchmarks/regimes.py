"""What each part of DIAMOND-SSS adds, per capture regime (issue 7; supplement Fig. 6, the paper's Table 1 analog).

Methods: `sss3dgs`; `diamond` without the multi-view losses; + multi-view losses; + relighting; + novel views +
relighting (the full pipeline). Regimes: all views x all lights, all views x 1 light, 5% x 5%, 3% x 3%.
Objects: synthetic objects NOT used for fine-tuning the diffusion models, rendered with `diamond-sss synth`
into outputs/benchmarks/objects (once; cached). Metrics on the test split (novel views under novel lights).
Runs go to outputs/benchmarks/regimes (resumable); regimes.json / regimes.md / regimes_grid.png are written to
benchmarks/results/regimes.

    python benchmarks/regimes.py --iterations 400 --objects torus:soap blob:marble
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.evaluation.ablation import regime_slug
from diamond_sss.evaluation.evaluate import render_observation
from diamond_sss.evaluation.figures import save_image_grid, to_display
from diamond_sss.pipeline.run import PipelineConfig, run_pipeline
from diamond_sss.synth.cli import synth
from diamond_sss.training.config import short_schedule
from diamond_sss.training.run import evaluate_run, train_run
from diamond_sss.training.trainer import load_scene

RESULTS = Path(__file__).resolve().parent / "results" / "regimes"
RUNS = Path("outputs") / "benchmarks" / "regimes"
OBJECTS = Path("outputs") / "benchmarks" / "objects"
REGIMES = ("all", "all-views-1-light", "views=5%,lights=5%", "views=3%,lights=3%")
METHODS = ("sss3dgs", "diamond-no-mv", "+mv", "+mv+relight", "+mv+nvs+relight")
# held-out objects: shape:material pairs that differ from the four fine-tuning objects
DEFAULT_OBJECTS = ("torus:soap", "blob:marble")


def ensure_object(spec: str, size: int, spp: int) -> Path:
    """Render ``shape:material`` once into outputs/benchmarks/objects (40 x 24 lattice, 8 x 6 test split)."""
    shape, material = spec.split(":")
    folder = OBJECTS / f"{shape}_{material}_{size}px_{spp}spp"
    if not (folder / "transforms_test.json").is_file():
        synth(shape=shape, material=material, out=folder, size=size, spp=spp, seed=7)
    return folder


def run_method(method: str, data: Path, run: Path, regime: str, iterations: int) -> dict:
    """Train and evaluate one method; returns the test metrics (+ synthetic image counts for the pipeline)."""
    overrides = short_schedule(iterations)
    if method in ("sss3dgs", "diamond-no-mv", "+mv"):
        preset = "sss3dgs" if method == "sss3dgs" else "diamond"
        if method == "diamond-no-mv":
            overrides.update(lambda_sil=0.0, lambda_depth=0.0)
        train_run(data, run, regime=regime, preset=preset, overrides=overrides, resume=True, show_progress=False)
        return evaluate_run(run, data, figures=0, show_progress=False)
    augment = ("relight",) if method == "+mv+relight" else ("nvs", "relight")
    return run_pipeline(data, run, regime=regime, preset="diamond", overrides=overrides,
                        config=PipelineConfig(augment=augment), show_progress=False)


def final_run(method: str, run: Path) -> Path:
    return run / "final" if method.startswith("+mv+") else run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", nargs="+", default=list(DEFAULT_OBJECTS), help="shape:material pairs")
    parser.add_argument("--regimes", nargs="+", default=list(REGIMES))
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--spp", type=int, default=128)
    parser.add_argument("--out", type=Path, default=RUNS)
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    rows = []
    for spec in args.objects:
        data = ensure_object(spec, args.size, args.spp)
        for regime in args.regimes:
            for method in args.methods:
                run = args.out / data.name / regime_slug(regime) / method
                started = time.perf_counter()
                metrics = run_method(method, data, run, regime, args.iterations)
                rows.append({"object": data.name, "regime": regime, "method": method,
                             "minutes": (time.perf_counter() - started) / 60, **metrics})
                print(json.dumps(rows[-1]), flush=True)
    lines = ["| object | regime | method | PSNR | SSIM | LPIPS | mask IoU | synthetic images |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lpips = "n/a" if r.get("lpips") is None else f"{r['lpips']:.4f}"
        lines.append(f"| {r['object']} | `{r['regime']}` | {r['method']} | {r['psnr']:.2f} | {r['ssim']:.4f} | "
                     f"{lpips} | {r['mask_iou']:.3f} | {r.get('synthetic_images', 0)} |")
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "regimes.json").write_text(json.dumps(rows, indent=2) + "\n")
    (args.results / "regimes.md").write_text("\n".join(lines) + "\n")
    data = ensure_object(args.objects[0], args.size, args.spp)
    test = OLATDataset(data, "test")
    grid = []
    for regime in args.regimes:
        row = [to_display(test.load(0).rgb)]
        for method in args.methods:
            scene, _ = load_scene(final_run(method, args.out / data.name / regime_slug(regime) / method))
            row.append(to_display(render_observation(scene, test, 0, "cpu").radiance[0]))
        grid.append(row)
    save_image_grid(args.results / "regimes_grid.png", grid, row_labels=list(args.regimes),
                    col_labels=["ground truth", *args.methods], title=f"{data.name}: test view 0, test light 0")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
