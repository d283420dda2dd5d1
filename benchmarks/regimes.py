"""What each stage of DIAMOND-SSS adds in the paper's sparse regimes, given as counts (issue 18).

Regimes: `views=3,lights=3` (9 images, the paper's 3% x 3%) and `views=5,lights=6` (30 images, 5% x 5%), and
the dense reference (`dense`: the `diamond` preset on every image). Rows per object, regime and stage:
`sss3dgs` (real images only); `+mv` (the `diamond` preset: + multi-view losses); `+relight` (+ relighting
diffusion); `full` (+ novel-view diffusion: the full pipeline), plus the mean over objects. The pipeline rows
reuse the `sss3dgs` run as their preliminary reconstruction. Every method trains for the same steps.
Objects: data folders or `shape:material` pairs never used for fine-tuning the diffusion models (those are
torus/jade, bust/marble, blob/soap, sphere/skin), rendered once with `diamond-sss synth` into
outputs/benchmarks/objects. Metrics on the test split (novel views under novel lights).

    python benchmarks/regimes.py --iterations 1000 --objects src/diamond_sss/assets/data/demo torus:soap blob:marble

Runs go to --out (resumable: a second call with the same arguments only collects); regimes.json, regimes.md and
regimes_grid.png go to --results. The targets: at 9 images `full` beats `sss3dgs` by >= 2 dB PSNR and in mask
IoU; at 30 images `full` is within 2 dB of `dense`.
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
RUNS = Path("outputs") / "benchmarks" / "regimes_counts"
OBJECTS = Path("outputs") / "benchmarks" / "objects"
NINE, THIRTY = "views=3,lights=3", "views=5,lights=6"
REGIMES = (NINE, THIRTY)
METHODS = ("sss3dgs", "+mv", "+relight", "full")
LABELS = {"sss3dgs": "sss3dgs (real images only)", "+mv": "+ multi-view losses", "+relight": "+ relighting",
          "full": "+ novel views (full pipeline)", "dense": "dense reconstruction (all images)"}
DEFAULT_OBJECTS = ("src/diamond_sss/assets/data/demo", "torus:soap", "blob:marble")
METRICS = ("psnr", "ssim", "mask_iou")


def resolve_object(spec: str, size: int, spp: int) -> Path:
    """An existing data folder as it is, else ``shape:material`` rendered once (40 x 24 lattice, 8 x 6 test)."""
    path = Path(spec)
    if path.is_dir():
        return path
    if spec.count(":") != 1:
        raise SystemExit(f"--objects: {spec!r} is neither a data folder nor a shape:material pair")
    shape, material = spec.split(":")
    folder = OBJECTS / f"{shape}_{material}_{size}px_{spp}spp"
    if not (folder / "transforms_test.json").is_file():
        synth(shape=shape, material=material, out=folder, size=size, spp=spp, seed=7)
    return folder


def run_method(method: str, data: Path, runs: Path, regime: str, iterations: int, tag: str = "",
               min_real_share: float = 0.0) -> tuple[Path, dict]:
    """Train and evaluate one method in ``runs/<method><tag>``; returns its final run folder and test metrics
    (+ image counts). The pipeline methods reuse ``runs/sss3dgs`` as their preliminary reconstruction."""
    overrides = short_schedule(iterations)
    if method in ("sss3dgs", "+mv", "dense"):
        run = runs / method
        if not (run / "model.safetensors").is_file():  # a finished run is not resumed (that retrains its last part)
            train_run(data, run, regime="all" if method == "dense" else regime,
                      preset="sss3dgs" if method == "sss3dgs" else "diamond", overrides=overrides, resume=True,
                      show_progress=False)
        metrics = evaluate_run(run, data, figures=0, show_progress=False)
        real = len(json.loads((run / "regime.json").read_text())["observations"])
        return run, {**metrics, "real_images": real, "synthetic_images": 0, "real_share": 1.0}
    prelim = runs / "sss3dgs"
    if not (prelim / "model.safetensors").is_file():
        run_method("sss3dgs", data, runs, regime, iterations)
    augment = ("relight",) if method == "+relight" else ("nvs", "relight")
    config = PipelineConfig(augment=augment, prelim_run=str(prelim), min_real_share=min_real_share)
    metrics = run_pipeline(data, runs / f"{method}{tag}", regime=regime, preset="diamond", overrides=overrides,
                           config=config, show_progress=False)
    return runs / f"{method}{tag}" / "final", metrics


def mean_rows(rows: list[dict]) -> list[dict]:
    """One row per (regime, method): the mean of each metric over the objects."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["regime"], row["method"]), []).append(row)
    return [{"object": f"mean ({len(group)})", "regime": regime, "method": method,
             **{key: sum(r[key] for r in group) / len(group) for key in (*METRICS, "synthetic_images")}}
            for (regime, method), group in groups.items()]


def target_lines(rows: list[dict], tag: str) -> list[str]:
    """The issue's two targets per object and for the mean, as Markdown bullet lines."""
    score = {(r["object"], r["regime"], r["method"]): r for r in rows}
    lines = []
    for name in dict.fromkeys(r["object"] for r in rows):
        full, base = score.get((name, NINE, f"full{tag}")), score.get((name, NINE, "sss3dgs"))
        if full and base:
            gain, iou = full["psnr"] - base["psnr"], full["mask_iou"] - base["mask_iou"]
            met = gain >= 2.0 and iou > 0
            lines.append(f"- {name}, 9 images: full - sss3dgs = {gain:+.2f} dB, mask IoU {iou:+.3f} "
                         f"(target >= +2 dB and > 0: {'met' if met else 'not met'})")
        full, dense = score.get((name, THIRTY, f"full{tag}")), score.get((name, "all", "dense"))
        if full and dense:
            gap = full["psnr"] - dense["psnr"]
            lines.append(f"- {name}, 30 images: full - dense = {gap:+.2f} dB (target >= -2 dB: "
                         f"{'met' if gap >= -2.0 else 'not met'})")
    return lines


def markdown(rows: list[dict], iterations: int, tag: str) -> str:
    lines = [f"{iterations} steps per reconstruction (`short_schedule`), test split (novel views under novel lights).",
             "", "| object | regime | stage | PSNR | SSIM | mask IoU | real / synthetic images |",
             "|---|---|---|---|---|---|---|"]
    for r in [*rows, *mean_rows(rows)]:
        method = r["method"]
        label = LABELS.get(method, LABELS.get(method.removesuffix(tag), method) + (f" [{tag}]" if tag else ""))
        images = f"{r.get('real_images', '')} / {r['synthetic_images']:.0f}"
        lines.append(f"| {r['object']} | `{r['regime']}` | {label} | {r['psnr']:.2f} | {r['ssim']:.4f} | "
                     f"{r['mask_iou']:.3f} | {images} |")
    return "\n".join([*lines, "", "Targets:", *target_lines(rows, tag)]) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", nargs="+", default=list(DEFAULT_OBJECTS),
                        help="data folders or shape:material pairs")
    parser.add_argument("--regimes", nargs="+", default=list(REGIMES))
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--no-dense", action="store_true", help="skip the dense reference")
    parser.add_argument("--iterations", type=int, default=1000)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--min-real-share", type=float, default=0.0,
                        help="lever: the pipeline's real images make up at least this share of the images drawn")
    parser.add_argument("--tag", default="", help="suffix of the pipeline rows' names, run folders and result "
                                                  "files (a lever's variant), e.g. _share50")
    parser.add_argument("--out", type=Path, default=RUNS)
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.min_real_share and not args.tag:
        parser.error("--min-real-share needs a --tag (its runs must not replace the plain pipeline's)")
    rows, finals = [], {}
    for spec in args.objects:
        data = resolve_object(spec, args.size, args.spp)
        jobs = [(regime, method) for regime in args.regimes for method in args.methods]
        jobs += [] if args.no_dense else [("all", "dense")]
        for regime, method in jobs:
            tagged = method if method in ("sss3dgs", "+mv", "dense") else f"{method}{args.tag}"
            runs = args.out / data.name / regime_slug(regime)
            started = time.perf_counter()
            final, metrics = run_method(method, data, runs, regime, args.iterations, args.tag, args.min_real_share)
            finals[data.name, regime, tagged] = final
            rows.append({"object": data.name, "regime": regime, "method": tagged,
                         "minutes": (time.perf_counter() - started) / 60,
                         **{k: metrics.get(k) for k in (*METRICS, "real_images", "synthetic_images", "real_share")}})
            print(json.dumps(rows[-1]), flush=True)
    args.results.mkdir(parents=True, exist_ok=True)
    name = f"regimes{args.tag}"
    (args.results / f"{name}.json").write_text(json.dumps({"iterations": args.iterations, "rows": rows,
                                                            "mean": mean_rows(rows)}, indent=2) + "\n")
    text = markdown(rows, args.iterations, args.tag)
    (args.results / f"{name}.md").write_text(text)
    first = resolve_object(args.objects[0], args.size, args.spp)
    test = OLATDataset(first, "test")
    columns = [key for key in finals if key[0] == first.name]
    grid = [[to_display(test.load(0).rgb)] + [to_display(render_observation(load_scene(finals[key])[0], test, 0,
                                                                            "cpu").radiance[0]) for key in columns]]
    save_image_grid(args.results / f"{name}_grid.png", grid, col_labels=["ground truth", *[
        f"{'9' if k[1] == NINE else '30' if k[1] == THIRTY else 'all'}: {k[2]}" for k in columns]],
        title=f"{first.name}: test view 0, test light 0")
    print(text)


if __name__ == "__main__":
    main()
