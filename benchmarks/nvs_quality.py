"""Novel-view model quality on held-out synthetic objects vs. a Gaussian reconstruction of the same input.

For each object (never one of the fine-tuning objects) and its light 0, the reference view generates every
other view; PSNR / SSIM (sRGB, full frame) and mask IoU against the rendered ground truth are binned by the
angle between target and reference cameras. Baseline: the relightable Gaussian model trained (short CPU
schedule) on the same single reference image, rendered at the target cameras under the same light; the
reference image itself, copied to every target, is reported as the trivial floor ("reference-copy"), and
the geometric warp hint alone ("warp-hint": the reference forward-warped with its depth, exactly as a
warp-hint model sees it, upsampled to the image size). The model and the hint take the reference's metric
depth from ``--geometry`` (default: the depth maps stored with the data, so render them); ``--depth-noise
RELATIVE EDGE_PX`` perturbs that depth as the fine-tuning's ``depth_noise_*`` does (every map, ``sigma =
RELATIVE``), to measure what a sparse reconstruction's depth costs the model (``benchmarks/sparse_depth.py``).
Writes benchmarks/results/nvs_quality/{nvs_quality.json, nvs_quality.md} (scratch runs: outputs/benchmarks/nvs_quality/).

    python -m diamond_sss.cli.main synth --shape torus --material marble --seed 21 --out /tmp/nvs/torus \\
        --views 12 --lights 1 --size 64 --spp 32 --test-views 0 --test-lights 0
    python benchmarks/nvs_quality.py --data /tmp/nvs/torus /tmp/nvs/bunny --baseline-iterations 150
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import torch
from torch import Tensor

from diamond_sss.data import DataError, OLATDataset
from diamond_sss.data.images import load_rgba
from diamond_sss.diffusion.common.manifest import read_image_manifest
from diamond_sss.diffusion.geometry import GeometryMaps, GeometrySource, geometry_source
from diamond_sss.diffusion.nvs.depth_noise import move_outline, smooth_relative_error
from diamond_sss.diffusion.nvs.model import NVSModel
from diamond_sss.diffusion.nvs.pipeline import (
    TargetCameras,
    default_model_dir,
    generate_novel_views,
    warp_reference_views,
)
from diamond_sss.diffusion.nvs.rays import view_angle_degrees
from diamond_sss.evaluation.metrics import image_metrics
from diamond_sss.pipeline.capture import lattice_header
from diamond_sss.runs.folder import load_scene
from diamond_sss.training.config import short_schedule
from diamond_sss.training.run import train_from_preset

RESULTS = Path(__file__).resolve().parent / "results" / "nvs_quality"
WORK = Path(__file__).resolve().parents[1] / "outputs" / "benchmarks" / "nvs_quality"
"""Scratch folder of the baseline runs and generated images (outside the committed results)."""
ANGLE_BINS = ((0, 30), (30, 60), (60, 90), (90, 181))


class PerturbedDepth(GeometrySource):
    """``source``'s maps with their depth's outline moved by ``edge_px`` pixels and a smooth relative error of
    standard deviation ``relative`` (:mod:`diamond_sss.diffusion.nvs.depth_noise`), drawn from ``seed`` and the view."""

    def __init__(self, source: GeometrySource, relative: float, edge_px: int, seed: int = 0) -> None:
        self.source, self.relative, self.edge_px, self.seed = source, relative, edge_px, seed

    def maps(self, dataset: OLATDataset, view: int, image: Tensor, mask: Tensor) -> GeometryMaps:
        maps = self.source.maps(dataset, view, image, mask)
        depth = maps.depth.permute(2, 0, 1)[None]
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + view)
        depth = move_outline(depth, self.edge_px)
        depth = depth * smooth_relative_error(depth, self.relative, generator) * (depth > 0)
        return dataclasses.replace(maps, depth=depth[0].permute(1, 2, 0))

    def key(self) -> dict:
        return {"kind": "perturbed", "source": self.source.key(), "relative": self.relative,
                "edge_px": self.edge_px, "seed": self.seed}


def single_image_capture(data: Path, view: int, light: int, out: Path) -> Path:
    """A capture folder holding only image ``(view, light)`` of ``data`` (either transforms format): one frame
    with that view's camera, that light and the original image (and mask file, if any); no geometry maps."""
    dataset = OLATDataset(data, "train")
    obs = dataset.observations[dataset.observation_index(view, light)]
    lattice = lattice_header(dataset)
    lit = lattice["lights"][light]
    frame = {
        **lattice["cameras"][view],
        "file_paths": [str(obs.image_path)],
        "light_positions": [lit["position"]],
        "light_intensities": [lit["intensity"]],
    }
    if obs.mask_path is not None:
        frame["mask_paths"] = [str(obs.mask_path)]
    out.mkdir(parents=True, exist_ok=True)
    (out / "transforms_train.json").write_text(json.dumps({"frames": [frame]}))
    return out


def baseline_renders(data: Path, view: int, light: int, targets: list[int], out: Path, iterations: int):
    """Linear RGB ``[T,H,W,3]`` and alpha ``[T,H,W,1]`` of Gaussians fitted to the one reference image."""
    dataset = OLATDataset(data, "train")
    capture = single_image_capture(data, view, light, out / "capture")
    overrides = {**short_schedule(iterations), "device": "cpu", "lambda_lpips": 0.0}
    train_from_preset(capture, out / "run", overrides=overrides, resume=True, show_progress=False)
    scene, _ = load_scene(out / "run")
    n = len(targets)
    with torch.no_grad():
        render = scene.render(
            dataset.viewmats[targets],
            dataset.intrinsics[targets],
            dataset.width,
            dataset.height,
            dataset.light_positions[light].expand(n, 3),
            dataset.light_intensities[light].expand(n, 3),
        )
    return render.radiance.clamp(0, 1), render.gbuffer.alpha


def evaluate_object(
    data: Path,
    model: Path,
    out: Path,
    view: int,
    light: int,
    steps: list[int],
    guidance: float,
    iterations: int,
    geometry: GeometrySource,
) -> list[dict]:
    """Per-image metrics of the model (one method per DDIM step count), the warp hint and the baselines."""
    dataset = OLATDataset(data, "train")
    targets = [v for v in range(dataset.num_views) if v != view and bool(dataset.presence[v, light])]
    predictions = {}
    for count in steps:
        started = time.perf_counter()
        folder = out / f"nvs_{count}"
        manifest = generate_novel_views(
            data,
            folder,
            view,
            light,
            targets,
            model_dir=model,
            steps=count,
            guidance_scale=guidance,
            cache_dir=out / "cache",
            geometry=geometry,
        )
        images = [load_rgba(item.image) for item in read_image_manifest(manifest)]
        predictions[f"nvs-{count}-steps"] = images
        print(f"{data.name}: nvs ({count} steps) {time.perf_counter() - started:.1f} s")
    config = NVSModel.read_config(model)
    cameras = TargetCameras.from_views(dataset, targets)
    warped = warp_reference_views(dataset, view, light, cameras, geometry, config).clamp(0, 1)
    predictions["warp-hint"] = [(w[:3].permute(1, 2, 0), w[3:].permute(1, 2, 0)) for w in warped]
    reference = dataset.load(dataset.observation_index(view, light))
    predictions["reference-copy"] = [(reference.rgb, reference.mask)] * len(targets)
    started = time.perf_counter()
    base_rgb, base_alpha = baseline_renders(data, view, light, targets, out / "baseline", iterations)
    predictions["gaussians"] = list(zip(base_rgb, base_alpha))
    print(f"{data.name}: baseline {time.perf_counter() - started:.1f} s")
    angles = view_angle_degrees(dataset.viewmats[targets], dataset.viewmats[view].expand(len(targets), 4, 4))
    rows = []
    for i, target in enumerate(targets):
        truth = dataset.load(dataset.observation_index(target, light))
        for method, images in predictions.items():
            rgb, alpha = images[i]
            m = image_metrics(rgb, truth.rgb, alpha, truth.mask)
            rows.append(
                {
                    "object": data.name,
                    "view": target,
                    "angle": float(angles[i]),
                    "method": method,
                    "psnr": m.psnr,
                    "ssim": m.ssim,
                    "mask_iou": m.mask_iou,
                }
            )
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    """Mean PSNR / SSIM / mask IoU per angle bin and method (bins in order, methods in order of first row)."""
    table = []
    for low, high in ANGLE_BINS:
        for method in dict.fromkeys(r["method"] for r in rows):
            sel = [r for r in rows if r["method"] == method and low <= r["angle"] < high]
            if sel:
                table.append(
                    {
                        "angles": f"{low}-{min(high, 180)}",
                        "method": method,
                        "images": len(sel),
                        **{k: sum(r[k] for r in sel) / len(sel) for k in ("psnr", "ssim", "mask_iou")},
                    }
                )
    return table


def markdown_table(table: list[dict]) -> str:
    """The rows of :func:`summarise` as a Markdown table."""
    lines = [
        "| angle from reference (deg) | method | images | PSNR | SSIM | mask IoU |",
        "|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['angles']} | {r['method']} | {r['images']} | {r['psnr']:.2f} | {r['ssim']:.4f} | "
        f"{r['mask_iou']:.3f} |"
        for r in table
    ]
    return "\n".join(lines)


def settings_record(args: argparse.Namespace) -> dict:
    """The command line as JSON values (paths as strings; the model "shipped" when not given), recorded with the
    results."""
    settings = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    settings["data"] = [str(d) for d in args.data]
    settings["model"] = str(args.model or "shipped")
    return settings


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line ``argv`` (default: the process's)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="held-out synthetic captures")
    parser.add_argument(
        "--model", type=Path, default=None, help="NVS model folder (default: the shipped one)"
    )
    parser.add_argument("--view", type=int, default=0, help="reference view")
    parser.add_argument("--light", type=int, default=0)
    parser.add_argument("--steps", type=int, nargs="+", default=[25, 1], help="DDIM step counts to compare")
    parser.add_argument("--guidance", type=float, default=2.0)
    parser.add_argument("--baseline-iterations", type=int, default=150)
    parser.add_argument(
        "--geometry", default="maps", help="reference depth for the warp hint: 'maps' or a run folder"
    )
    parser.add_argument("--depth-noise", type=float, nargs=2, default=None, metavar=("RELATIVE", "EDGE_PX"),
                        help="perturb the reference depth: a smooth relative error of this standard deviation and "
                             "the outline moved by EDGE_PX pixels (> 0 dilates)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="folder of nvs_quality.{json,md}")
    parser.add_argument("--work", type=Path, default=WORK,
                        help="folder of the baseline runs and generated images, one subfolder per capture")
    args = parser.parse_args(argv)
    if args.depth_noise is not None:
        relative, edge = args.depth_noise
        if not (math.isfinite(relative) and relative >= 0 and math.isfinite(edge) and edge == int(edge)):
            parser.error(f"--depth-noise {relative:g} {edge:g}: RELATIVE must be a finite number >= 0 and EDGE_PX "
                         "a whole number of pixels")
    return args


def check_reference(args: argparse.Namespace) -> None:
    """Stop, naming the option, its value and the valid range, unless every ``--data`` capture has image
    ``(--view, --light)``; done before any work."""
    for data in args.data:
        try:
            dataset = OLATDataset(data, "train")
        except DataError as exc:
            raise SystemExit(f"--data: {exc}") from exc
        for option, value, count, what in (("--view", args.view, dataset.num_views, "views"),
                                           ("--light", args.light, dataset.num_lights, "lights")):
            if not 0 <= value < count:
                raise SystemExit(f"{option} {value} is out of range for {data}: its {what} are 0..{count - 1}")
        if not dataset.presence[args.view, args.light]:
            raise SystemExit(f"--view {args.view} --light {args.light}: {data} has no image of view {args.view} "
                             f"under light {args.light}")


def main() -> None:
    args = parse_args()
    check_reference(args)
    model = args.model or default_model_dir()
    geometry = geometry_source(args.geometry)
    if args.depth_noise is not None:
        geometry = PerturbedDepth(geometry, args.depth_noise[0], int(args.depth_noise[1]))
    rows = []
    for data in args.data:
        rows += evaluate_object(
            data,
            model,
            args.work / data.name,
            args.view,
            args.light,
            args.steps,
            args.guidance,
            args.baseline_iterations,
            geometry,
        )
    table = summarise(rows)
    text = markdown_table(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "nvs_quality.json").write_text(
        json.dumps({"settings": settings_record(args), "summary": table, "images": rows}, indent=2) + "\n"
    )
    (args.out / "nvs_quality.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
