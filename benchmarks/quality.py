"""Reconstruction quality and where its error is, beside the data's noise ceiling (issue 17).

Each variant is a preset plus config overrides, trained on one capture regime with the same schedule
(``short_schedule(--iterations)``, with the dense budget for ``--regime all``), then scored on the test split (novel views under novel lights) and on
training images (can it fit at all?), with the test error split by region (``evaluation/regions.py``:
silhouette, back-lit, cast shadow, highlight, lit). The noise ceiling comes from a second render of the test
split with independent Monte Carlo noise (``evaluation/noise.py``), rendered once from the capture's
``meta.json`` with ``--render-noise-reference`` (Mitsuba) or given with ``--noise-reference``. With
``--cross-splits`` each variant is also scored on novel views under training lights and on training views under
novel lights (``diamond-sss synth --cross-splits``; rendered into the noise reference when the data lacks them),
which splits the test error into what a novel view and a novel light cost.

    python benchmarks/quality.py --iterations 1000 --render-noise-reference \\
        --variants base "srgb:photometric_space=srgb" "mlp64:sss_width=64,sss_lr=0.005"

Runs go to outputs/benchmarks/quality/<data>/<regime>/<variant>-<hash of its settings> (resumable); the table,
JSON and region figures to benchmarks/results/quality/.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import time
from pathlib import Path

import torch

from diamond_sss.data.dataset import OLATDataset, directions_from
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.data.regimes import nearest_angle_deg
from diamond_sss.evaluation.noise import noise_ceiling
from diamond_sss.evaluation.regions import region_errors, save_region_figure
from diamond_sss.evaluation.run import evaluate_run
from diamond_sss.experiments.ablation import regime_slug
from diamond_sss.runs.folder import load_scene
from diamond_sss.training.config import short_schedule
from diamond_sss.training.overrides import parse_sets
from diamond_sss.training.run import train_from_preset

RESULTS = Path(__file__).resolve().parent / "results" / "quality"
RUNS = Path("outputs") / "benchmarks" / "quality"
REGION_COLUMNS = ("silhouette", "back_lit", "shadow", "lit")
TRAIN_IMAGES = 96
CROSS_SPLITS = ("novel_view", "novel_light")


def parse_variant(text: str) -> tuple[str, dict]:
    """``"name:key=value,key=value"`` (or just ``"name"``) -> ``(name, typed overrides)``."""
    name, _, body = text.partition(":")
    try:
        return name, parse_sets([item for item in body.split(",") if item])
    except ValueError as exc:
        raise SystemExit(f"--variants {text!r}: {exc}") from exc


def settings_hash(preset: str, overrides: dict) -> str:
    return hashlib.sha256(json.dumps([preset, overrides], sort_keys=True).encode()).hexdigest()[:8]


def noise_reference(data: Path, reference: Path | None, render: bool, cross_splits: bool, runs: Path) -> Path | None:
    """The folder of ``data``'s test split rendered again with independent noise (and, with ``cross_splits``, the
    ``novel_view`` / ``novel_light`` splits when ``data`` lacks them), rendering it first when asked."""
    if reference is not None or not (render or cross_splits):
        return reference
    from diamond_sss.data.errors import DataError
    from diamond_sss.synth.render import noise_reference_config, synthesize

    reference = runs / "noise_reference" / data.name
    needs_cross = cross_splits and not any(all((folder / f"transforms_{split}.json").is_file() for split in CROSS_SPLITS)
                                           for folder in (data, reference))
    if needs_cross or (render and not (reference / "transforms_test.json").is_file()):
        try:
            synthesize(noise_reference_config(data, reference, cross_splits=needs_cross))
        except DataError as exc:
            raise SystemExit(f"--render-noise-reference / --cross-splits: {exc}") from exc
    return reference if (reference / "transforms_test.json").is_file() else None


def cross_split_folder(data: Path, reference: Path | None) -> Path:
    """The folder that holds the ``novel_view`` and ``novel_light`` splits: ``data`` itself, else ``reference``."""
    for folder in (data, reference):
        if folder is not None and all((folder / f"transforms_{split}.json").is_file() for split in CROSS_SPLITS):
            return folder
    raise SystemExit(f"--cross-splits: neither {data} nor the noise reference {reference} holds "
                     f"transforms_novel_view.json and transforms_novel_light.json (render them with "
                     f"`diamond-sss synth --cross-splits`, or drop --noise-reference to render them here)")


def nearest_training_light_deg(train: OLATDataset, lights: list[int], test: OLATDataset) -> list[float]:
    """For each test light, the angle in degrees, seen from the scene centre, to the nearest of the training
    ``lights`` (indices into ``train``'s lights): how far a novel light lies from what the run was trained on."""
    center = train.bounds.center
    angles = nearest_angle_deg(directions_from(test.light_positions, center),
                               directions_from(train.light_positions[lights], center))
    return [round(angle, 1) for angle in angles.tolist()]


def per_light_psnr(per_image_csv: Path, num_lights: int) -> list[float]:
    """The mean PSNR of each light's images in an ``eval_<split>/per_image.csv`` (the mean over images, as the
    split's PSNR is), lights ``0..num_lights-1``; NaN for a light without images."""
    values: dict[int, list[float]] = {}
    with per_image_csv.open() as handle:
        for row in csv.DictReader(handle):
            values.setdefault(int(row["light"]), []).append(float(row["psnr"]))
    return [sum(values[light]) / len(values[light]) if light in values else math.nan for light in range(num_lights)]


def per_light_table(rows: list[dict], distances: list[list[float]]) -> list[str]:
    """Markdown: test PSNR per test light and per variant, each cell with the light's angle to the variant's nearest
    training light (deg)."""
    header = "| variant | " + " | ".join(f"light {i}: PSNR (deg)" for i in range(len(distances[0]))) + " |"
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for row, angles in zip(rows, distances, strict=True):
        cells = " | ".join(f"{psnr:.2f} ({angle:.0f})" for psnr, angle in zip(row["light_psnr"], angles, strict=True))
        lines.append(f"| {row['variant']} | {cells} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=None, help="data folder (default: the embedded demo)")
    parser.add_argument("--iterations", type=int, default=1000)
    parser.add_argument("--preset", default="diamond")
    parser.add_argument("--regime", default="all")
    parser.add_argument("--variants", nargs="+", default=["base"], help='"name:key=value,..." (base: no change)')
    parser.add_argument("--noise-reference", type=Path, default=None,
                        help="the test split rendered again with independent noise")
    parser.add_argument("--render-noise-reference", action="store_true",
                        help="render that second test split from the capture's meta.json (Mitsuba)")
    parser.add_argument("--cross-splits", action="store_true",
                        help="also score novel views under training lights and training views under novel lights")
    parser.add_argument("--out", type=Path, default=RUNS, help="run folders (resumable)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="where the tables and figures are written")
    parser.add_argument("--tag", default="quality", help="file name of the table (<tag>.md / <tag>.json)")
    args = parser.parse_args()
    data = args.data or embedded_dataset()
    reference = noise_reference(data, args.noise_reference, args.render_noise_reference, args.cross_splits, args.out)
    ceiling = noise_ceiling(OLATDataset(data, "test"), OLATDataset(reference, "test")) if reference else None
    cross = cross_split_folder(data, reference) if args.cross_splits else None
    ceiling_db = ceiling["ceiling_psnr"] if ceiling else math.nan
    test, train = OLATDataset(data, "test"), OLATDataset(data, "train")
    args.results.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, overrides in map(parse_variant, args.variants):
        settings = {**short_schedule(args.iterations, dense=args.regime == "all"), **overrides}
        run = args.out / data.name / regime_slug(args.regime) / f"{name}-{settings_hash(args.preset, settings)}"
        started = time.perf_counter()
        result = train_from_preset(data, run, regime=args.regime, preset=args.preset, overrides=settings,
                                   resume=True, show_progress=False)
        minutes = (time.perf_counter() - started) / 60
        scores = evaluate_run(run, data, split="test", figures=0, show_progress=False)
        fit = evaluate_run(run, data, split="train", figures=0, max_images=TRAIN_IMAGES, show_progress=False)
        split_psnr = {split: evaluate_run(run, cross, split=split, figures=0, show_progress=False)["psnr"]
                      for split in (CROSS_SPLITS if cross else ())}
        scene, _ = load_scene(run, torch.device("cpu"))
        regions = region_errors(scene, test).summary()
        save_region_figure(args.results / f"regions_{args.tag}_{name}.png", scene, test, [0, len(test) // 3, 2 * len(test) // 3],
                           title=f"{name}: {args.iterations} steps, test PSNR {scores['psnr']:.2f} dB")
        rows.append({"variant": name, "overrides": overrides, "preset": args.preset, "regime": args.regime,
                     "iterations": args.iterations, "gaussians": result.num_gaussians, "minutes": minutes,
                     "train_psnr": fit["psnr"], **{k: scores[k] for k in ("psnr", "ssim", "masked_psnr", "mask_iou")},
                     "regions": regions, "ceiling_psnr": ceiling_db, "split_psnr": split_psnr,
                     "light_psnr": per_light_psnr(run / "eval_test" / "per_image.csv", test.num_lights),
                     "nearest_training_light_deg": nearest_training_light_deg(
                         train, json.loads((run / "regime.json").read_text())["lights"], test)})
        print(f"{name}: test {scores['psnr']:.2f} dB, train {fit['psnr']:.2f} dB, {minutes:.1f} min", flush=True)
    cross_header = "novel view, training lights | training view, novel lights | " if cross else ""
    header = ("| variant | overrides | Gaussians | train PSNR | " + cross_header + "test PSNR | SSIM | masked PSNR | IoU | "
              + " | ".join(f"{r} PSNR (err %)" for r in REGION_COLUMNS) + " | ceiling | gap | min |")
    lines = [f"`{args.preset}`, regime `{args.regime}`, {args.iterations} steps (`short_schedule`), "
             f"{data.name}; ceiling: " + (f"{ceiling_db:.2f} dB (two renders differ by {ceiling['render_psnr']:.2f} "
                                          f"dB + 3.01)" if ceiling else "not measured"), "",
             header, "|" + "---|" * (header.count("|") - 1)]
    for r in rows:
        region_cells = " | ".join(f"{r['regions'][k]['psnr']:.1f} ({100 * r['regions'][k]['error_share']:.0f})"
                                  for k in REGION_COLUMNS)
        settings = ", ".join(f"{k}={v}" for k, v in r["overrides"].items()) or "-"
        cross_cells = "".join(f"{r['split_psnr'][split]:.2f} | " for split in r["split_psnr"])
        lines.append(f"| {r['variant']} | {settings} | {r['gaussians']} | {r['train_psnr']:.2f} | {cross_cells}"
                     f"{r['psnr']:.2f} | "
                     f"{r['ssim']:.4f} | {r['masked_psnr']:.2f} | {r['mask_iou']:.3f} | {region_cells} | "
                     f"{ceiling_db:.2f} | {ceiling_db - r['psnr']:.2f} | {r['minutes']:.1f} |")
    lines += ["", "Test PSNR per test light (angle to the nearest training light of the run's regime, deg):", "",
              *per_light_table(rows, [r["nearest_training_light_deg"] for r in rows])] if rows else []
    (args.results / f"{args.tag}.json").write_text(json.dumps({"ceiling": ceiling, "rows": rows}, indent=2) + "\n")
    (args.results / f"{args.tag}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
