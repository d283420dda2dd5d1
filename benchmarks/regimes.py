"""What each part of DIAMOND-SSS adds, per capture regime (issue 7; supplement Fig. 6, the paper's Table 1 analog).

Methods: `sss3dgs`; `diamond` without the multi-view losses; + multi-view losses; + relighting; + novel views +
relighting (the full pipeline). Regimes: all views x all lights, all views x 1 light, 5% x 5%, 3% x 3%.
Objects: synthetic objects NOT used for fine-tuning the diffusion models, rendered with `diamond-sss synth`
into outputs/benchmarks/objects (once; cached), or existing data folders (e.g. the embedded demo object,
src/diamond_sss/assets/data/demo, which no diffusion model was fine-tuned on). Metrics on the test split (novel views under novel lights).
Runs go to outputs/benchmarks/regimes (resumable); regimes.json / regimes.md / regimes_grid.png are written to
benchmarks/results/regimes.

    python benchmarks/regimes.py --iterations 400 --objects torus:soap blob:marble

Besides the table, it reports the issue's targets per object: the last method's gain over `sss3dgs` at
5% x 5% and 3% x 3% (target >= 2 dB), and its 5% x 5% score against `sss3dgs` on all views x all lights
(target: within 2 dB).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from diamond_sss.cli.synth_commands import synth
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.evaluation.evaluate import render_observation
from diamond_sss.evaluation.figures import save_image_grid, to_display
from diamond_sss.evaluation.run import evaluate_run
from diamond_sss.experiments.ablation import regime_slug
from diamond_sss.pipeline.run import PipelineConfig, run_pipeline
from diamond_sss.training.config import short_schedule
from diamond_sss.training.run import train_run
from diamond_sss.training.run_folder import load_scene

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


def resolve_object(spec: str, size: int, spp: int) -> Path:
    """An existing data folder as it is, else ``shape:material`` rendered by :func:`ensure_object`."""
    path = Path(spec)
    if path.is_dir():
        return path
    if spec.count(":") != 1:
        raise SystemExit(f"--objects: {spec!r} is neither a data folder nor a shape:material pair")
    return ensure_object(spec, size, spp)


def target_lines(rows: list[dict], method: str) -> list[str]:
    """The issue's targets for ``method`` (see the module doc), per object, as Markdown bullet lines."""
    psnr = {(r["object"], r["regime"], r["method"]): r["psnr"] for r in rows}
    lines = []
    for name in dict.fromkeys(r["object"] for r in rows):
        for regime in ("views=5%,lights=5%", "views=3%,lights=3%"):
            if (name, regime, method) in psnr and (name, regime, "sss3dgs") in psnr:
                gain = psnr[name, regime, method] - psnr[name, regime, "sss3dgs"]
                lines.append(f"- {name}, `{regime}`: {method} - sss3dgs = {gain:+.2f} dB (target >= +2 dB: "
                             f"{'met' if gain >= 2.0 else 'not met'})")
        sparse, dense = (name, "views=5%,lights=5%", method), (name, "all", "sss3dgs")
        if sparse in psnr and dense in psnr:
            gap = psnr[sparse] - psnr[dense]
            lines.append(f"- {name}: {method} at 5% x 5% - sss3dgs on all images = {gap:+.2f} dB (target >= -2 dB: "
                         f"{'met' if gap >= -2.0 else 'not met'})")
    return lines


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
    parser.add_argument("--objects", nargs="+", default=list(DEFAULT_OBJECTS),
                        help="shape:material pairs or data folders")
    parser.add_argument("--regimes", nargs="+", default=list(REGIMES))
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument("--dense-methods", nargs="+", default=None,
                        help="methods run in the `all` regime (default: --methods; the pipeline generates nothing there)")
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--spp", type=int, default=128)
    parser.add_argument("--out", type=Path, default=RUNS)
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    rows = []
    for spec in args.objects:
        data = resolve_object(spec, args.size, args.spp)
        for regime in args.regimes:
            for method in (args.dense_methods or args.methods) if regime == "all" else args.methods:
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
    lines += ["", f"Targets ({args.methods[-1]}):", *target_lines(rows, args.methods[-1])]
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "regimes.json").write_text(json.dumps(rows, indent=2) + "\n")
    (args.results / "regimes.md").write_text("\n".join(lines) + "\n")
    data = resolve_object(args.objects[0], args.size, args.spp)
    test = OLATDataset(data, "test")
    grid = []
    for regime in args.regimes:
        row = [to_display(test.load(0).rgb)]
        for method in args.methods:
            if regime == "all" and method not in (args.dense_methods or args.methods):
                row.append(np.zeros_like(row[0]))
                continue
            scene, _ = load_scene(final_run(method, args.out / data.name / regime_slug(regime) / method))
            row.append(to_display(render_observation(scene, test, 0, "cpu").radiance[0]))
        grid.append(row)
    save_image_grid(args.results / "regimes_grid.png", grid, row_labels=list(args.regimes),
                    col_labels=["ground truth", *args.methods], title=f"{data.name}: test view 0, test light 0")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
