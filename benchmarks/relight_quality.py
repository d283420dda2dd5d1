"""Relighting model quality on held-out synthetic objects vs. two baselines (issue 5).

For each object (never one of the fine-tuning objects) and each view with several lights, the image under
the view's first light is relit to every other light and compared with the rendered ground truth:
PSNR / SSIM on sRGB images in [0,1], full frame, black background. Baselines: the unchanged source image,
and Lambertian re-shading from the stored normals (``diamond_sss.diffusion.relight.baselines``). The model
and the Lambertian baseline use the same stored depth / normal maps (``--geometry maps``). The row ``hint``
is the model's own input, the shading hint with its fitted scattering (``diamond_sss.diffusion.relight.hint``),
to show what the network adds to it.

The held-out set: nine objects covering the six materials, none of them a fine-tuning object (those are
blob/soap, bust/marble, sphere/skin, torus/jade) or a validation object used to choose the hint and the model
(blob/jade, bunny/skin, bust/soap, sphere/glazed_wax):

    for spec in bunny:glazed_wax:11 blob:wax:12 torus:marble:13 torus:skin:31 bunny:jade:32 sphere:marble:33 \
        bust:wax:34 blob:glazed_wax:35 sphere:soap:36; do IFS=: read -r s m seed <<< "$spec"
      diamond-sss synth --shape $s --material $m --seed $seed --out /tmp/relight_bench/heldout/${s}_${m} \
        --views 40 --lights 24 --test-views 0 --test-lights 0 --size 64 --spp 64 --subset relight:2x8; done
    python benchmarks/relight_quality.py --data /tmp/relight_bench/heldout/*
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.diffusion.common.cache import OutputCache
from diamond_sss.diffusion.geometry import StoredMapsGeometry
from diamond_sss.diffusion.relight.baselines import lambertian_relight
from diamond_sss.diffusion.relight.conditioning import conditioning_image, model_to_image
from diamond_sss.diffusion.relight.config import RelightModelConfig
from diamond_sss.diffusion.relight.hint import configured_fit, relit_hint
from diamond_sss.diffusion.relight.inference import load_model, relight_view
from diamond_sss.diffusion.relight.light import light_code
from diamond_sss.errors import DataError
from diamond_sss.evaluation.figures import save_image_grid, to_display
from diamond_sss.evaluation.metrics import image_metrics

METHODS = ("model", "source", "lambertian", "hint")
FIGURE_METHODS = ("lambertian", "hint", "model")
RESULTS = Path(__file__).resolve().parent / "results" / "relight_quality"


def shading_hint(model, conditioning: Tensor, target_codes: Tensor, source_code: Tensor) -> Tensor:
    """The model's own hint, or the default configuration's for a model trained without one; the scattering
    is fitted once to the view's source ``conditioning[:1]`` lit by ``source_code [10]``."""
    fit = model.scattering_fit(conditioning[:1], source_code[None])
    if fit is None:
        fit = configured_fit(RelightModelConfig(), conditioning[:1], source_code[None])
    return relit_hint(conditioning, target_codes, fit.expand(target_codes.shape[0]))


def multi_light_views(dataset: OLATDataset) -> list[int]:
    """The views with images under 2 or more lights."""
    return [view for view in range(dataset.num_views) if int(dataset.presence[view].sum()) >= 2]


def relightable_views(dataset: OLATDataset) -> list[int]:
    """The views the benchmark relights: images under 2 or more lights and stored depth / normal maps."""
    return [view for view in multi_light_views(dataset) if dataset.has_geometry_maps(view)]


def usable_objects(roots: list[Path]) -> list[Path]:
    """The object folders with a view to relight (images under 2 or more lights, stored depth / normal maps); a
    warning on stderr names each other folder and why; stops when there is none."""
    usable = []
    for root in roots:
        try:
            dataset = OLATDataset(root)
        except DataError as exc:
            raise SystemExit(f"--data: {exc}") from exc
        if relightable_views(dataset):
            usable.append(root)
            continue
        why = ("no view with images under 2 or more lights has stored depth / normal maps "
               "('depth_path' / 'normal_path')" if multi_light_views(dataset) else
               "no view has images under 2 or more lights")
        print(f"warning: skipping {root}: {why}", file=sys.stderr)
    if not usable:
        raise SystemExit(f"no object to evaluate among the {len(roots)} folder(s) of --data: relighting needs a "
                         "view with images under 2 or more lights and stored depth / normal maps")
    return usable


def evaluate_object(
    root: Path, model, steps: int, samples: int, seed: int, cache: OutputCache
) -> tuple[list[dict], list[np.ndarray]]:
    """Per-image rows ``{object, view, source_light, light, method, psnr, ssim}`` of one object, and the figure row
    of its first relit image (source, each method, ground truth)."""
    dataset = OLATDataset(root)
    rows, figure_row = [], []
    geometry = StoredMapsGeometry()
    for view in relightable_views(dataset):
        lights = [int(i) for i in torch.nonzero(dataset.presence[view])[:, 0]]
        source_light, targets = lights[0], lights[1:]
        source = dataset.load(dataset.observation_index(view, source_light))
        depth, normals = dataset.load_geometry_maps(view)
        maps = geometry.maps(dataset, view, source.rgb, source.mask)
        size = source.rgb.shape[0]
        conditioning = conditioning_image(
            source.rgb[None], maps.nearness[None], maps.normals[None], source.mask[None], size
        ).expand(len(targets), -1, -1, -1)
        bounds = dataset.bounds
        codes = light_code(
            dataset.light_positions,
            dataset.viewmats[view].expand(dataset.num_lights, 4, 4),
            bounds.center,
            bounds.radius,
        )
        predictions = {
            "model": [
                r.rgb
                for r in relight_view(
                    model,
                    dataset,
                    view,
                    source_light,
                    targets,
                    geometry,
                    cache,
                    num_steps=steps,
                    seed=seed,
                    samples=samples,
                )
            ],
            "source": [source.rgb] * len(targets),
            "lambertian": list(
                lambertian_relight(
                    source.rgb,
                    source.mask,
                    depth,
                    normals,
                    dataset.viewmats[view],
                    dataset.intrinsics[view],
                    dataset.light_positions[source_light],
                    dataset.light_positions[targets],
                )
            ),
            "hint": list(model_to_image(shading_hint(model, conditioning, codes[targets], codes[source_light]))),
        }
        for i, light in enumerate(targets):
            truth = dataset.load(dataset.observation_index(view, light))
            if not figure_row:
                images = [source.rgb] + [predictions[m][i] for m in FIGURE_METHODS] + [truth.rgb]
                figure_row = [to_display(image) for image in images]
            for method in METHODS:
                metrics = image_metrics(predictions[method][i], truth.rgb, source.mask, truth.mask)
                rows.append(
                    {
                        "object": root.name,
                        "view": view,
                        "source_light": source_light,
                        "light": light,
                        "method": method,
                        "psnr": metrics.psnr,
                        "ssim": metrics.ssim,
                    }
                )
    return rows, figure_row


def summarize(rows: list[dict]) -> dict:
    """Mean PSNR / SSIM per method, overall and per object, and the model's margin over each baseline."""

    def mean(values: list[float]) -> float:
        return sum(values) / len(values)

    summary = {"images": len(rows) // len(METHODS), "overall": {}, "per_object": {}}
    for method in METHODS:
        chosen = [r for r in rows if r["method"] == method]
        summary["overall"][method] = {
            "psnr": mean([r["psnr"] for r in chosen]),
            "ssim": mean([r["ssim"] for r in chosen]),
        }
        for name in sorted({r["object"] for r in rows}):
            mine = [r for r in chosen if r["object"] == name]
            summary["per_object"].setdefault(name, {})[method] = {
                "psnr": mean([r["psnr"] for r in mine]),
                "ssim": mean([r["ssim"] for r in mine]),
            }
    overall = summary["overall"]
    summary["margin_db"] = {
        b: overall["model"]["psnr"] - overall[b]["psnr"] for b in ("source", "lambertian")
    }
    summary["beats_baselines_by_2db"] = all(m >= 2.0 for m in summary["margin_db"].values())
    return summary


def run_settings(args: argparse.Namespace, objects: list[Path]) -> dict:
    """The settings recorded with the results: the model ("shipped" when not given), sampling, the object folders
    evaluated (``--data`` less those without a view to relight)."""
    return {
        "model": str(args.model or "shipped"),
        "steps": args.steps,
        "samples": args.samples,
        "seed": args.seed,
        "objects": [str(p) for p in objects],
    }


def report_lines(summary: dict) -> list[str]:
    """The printed report of :func:`summarize`: mean PSNR / SSIM per method, PSNR per object, the margins."""
    lines = [f"{'method':<12}{'PSNR':>8}{'SSIM':>8}"]
    for method, values in summary["overall"].items():
        lines.append(f"{method:<12}{values['psnr']:>8.2f}{values['ssim']:>8.3f}")
    lines += ["", f"{'object (PSNR)':<20}" + "".join(f"{m:>12}" for m in METHODS)]
    for name, values in summary["per_object"].items():
        lines.append(f"{name:<20}" + "".join(f"{values[m]['psnr']:>12.2f}" for m in METHODS))
    lines.append(
        f"margin over baselines (dB): {summary['margin_db']}; beats both by 2 dB: {summary['beats_baselines_by_2db']}"
    )
    return lines


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line ``argv`` (default: the process's)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="held-out object folders")
    parser.add_argument("--model", type=Path, default=None, help="model folder (default: the shipped model)")
    parser.add_argument("--steps", type=int, default=1, help="DDIM steps")
    parser.add_argument("--samples", type=int, default=8, help="samples averaged per image")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    return parser.parse_args(argv)


def main() -> None:
    args = parse_args()
    objects = usable_objects(args.data)
    model = load_model(args.model).eval()
    rows, figure = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for root in objects:
            object_rows, figure_row = evaluate_object(
                root, model, args.steps, args.samples, args.seed, OutputCache(tmp)
            )
            rows += object_rows
            figure.append(figure_row)
    summary = summarize(rows)
    summary["settings"] = run_settings(args, objects)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "relight_quality.json").write_text(
        json.dumps({"summary": summary, "rows": rows}, indent=2) + "\n"
    )
    save_image_grid(
        args.out / "relight_quality.png",
        figure,
        row_labels=[p.name for p in objects],
        col_labels=["source", *FIGURE_METHODS, "ground truth"],
        title="relighting held-out objects: first relit image of each",
    )
    print("\n".join(report_lines(summary)))


if __name__ == "__main__":
    main()
