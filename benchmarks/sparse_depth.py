"""How wrong is the depth a sparse reconstruction renders at its own views? The warp hint's input at inference.

For every real view of each reconstruction run (its ``regime.json``), the depth the novel-view pipeline warps
with (:class:`~diamond_sss.diffusion.geometry.sources.RenderedGeometry`: rendered camera z where alpha > 0.5) is
compared with the capture's stored true depth, and so is the true depth perturbed by
:func:`~diamond_sss.diffusion.nvs.depth_noise.perturb_depth` with the ``finetune-nvs`` settings given, the same
statistics side by side, so that the fine-tuning's depth noise is calibrated against the error it stands for:

- ``iou``: the supports' (``z > 0``) intersection over union;
- ``outline_px``: the dilation (> 0) or erosion (< 0) of the true support, in pixels, that best matches the other;
- ``far_added``: support pixels more than 2 pixels outside the true support, as a share of the true support
  (membranes over holes, floaters);
- ``median_rel`` / ``spread_rel``: median and half the 16-84 percentile range of ``(z - z_true) / z_true`` where
  both have support;
- ``smooth_share``: 1 - the share of that error's variance in its difference from its 9 x 9 box blur (1: all
  low-frequency, a linear ramp ~0.96; 0: pixel noise).

    python benchmarks/sparse_depth.py --runs outputs/benchmarks/regimes_counts/*/views3_lights3/sss3dgs \
        outputs/benchmarks/regimes_counts/*/views5_lights6/sss3dgs --noise share=1 relative=0.15 edge_px=1 \
        --tag s30

Writes ``<tag>.{md,json}`` and ``<tag>.png`` (per view: true | rendered | perturbed depth, and the rendered depth's
relative error, blue = too near, red = too far, +-20%) to --results.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from matplotlib import colormaps
from torch import Tensor

from diamond_sss.data import DataError, OLATDataset
from diamond_sss.diffusion.geometry.sources import RenderedGeometry
from diamond_sss.diffusion.nvs.depth_noise import dilate, erode, perturb_depth
from diamond_sss.evaluation.figures import save_image_grid

RESULTS = Path(__file__).resolve().parent / "results" / "sparse_depth"
OUTLINE_RANGE = range(-4, 5)
STATS = ("iou", "outline_px", "far_added", "median_rel", "spread_rel", "smooth_share")
ERROR_RANGE = 0.2
"""Relative depth error at the ends of the figure's colour scale."""


def depth_stats(depth: Tensor, truth: Tensor) -> dict[str, float]:
    """The module docstring's statistics of camera-z map ``depth [1,1,H,W]`` against ``truth`` (0 = background)."""
    have, true = (depth > 0).float(), (truth > 0).float()
    union = ((have + true) > 0).sum()
    iou = float((have * true).sum() / union.clamp_min(1))
    moved = [(float((dilate(true, e) if e > 0 else erode(true, -e)).eq(have).float().mean()), -abs(e), e)
             for e in OUTLINE_RANGE]
    far = float((have * (1 - dilate(true, 2))).sum() / true.sum().clamp_min(1))
    both = (have * true) > 0
    rel = torch.where(both, (depth - truth) / truth.clamp_min(1e-9), 0.0)
    values = rel[both]
    if values.numel() < 2:
        return {"iou": iou, "outline_px": float(max(moved)[2]), "far_added": far, "median_rel": float("nan"),
                "spread_rel": float("nan"), "smooth_share": float("nan")}
    low, mid, high = torch.quantile(values.double(), torch.tensor([0.16, 0.5, 0.84], dtype=torch.float64))
    centred = torch.where(both, rel - values.mean(), 0.0)
    weight = F.avg_pool2d(both.float(), 9, stride=1, padding=4)
    blurred = F.avg_pool2d(centred, 9, stride=1, padding=4) / weight.clamp_min(1e-9)
    smooth = 1 - float((centred - blurred)[both].var() / centred[both].var().clamp_min(1e-18))
    return {"iou": iou, "outline_px": float(max(moved)[2]), "far_added": far, "median_rel": float(mid),
            "spread_rel": float((high - low) / 2), "smooth_share": max(smooth, 0.0)}


def depth_panels(truth: Tensor, rendered: Tensor, perturbed: Tensor) -> list[np.ndarray]:
    """Display images ``[H,W,3]`` of three camera-z maps ``[1,1,H,W]`` (one shared scale, background black) and of
    the rendered map's relative error (``coolwarm``, +-:data:`ERROR_RANGE`, white where either map is empty)."""
    near, far = float(truth[truth > 0].min()), float(truth.max())
    panels = []
    for depth in (truth, rendered, perturbed):
        scaled = ((depth[0, 0] - near) / max(far - near, 1e-9)).clamp(0, 1).numpy()
        panels.append(np.where((depth[0, 0] > 0).numpy()[..., None], colormaps["viridis"](scaled)[..., :3], 0.0))
    both = ((truth > 0) & (rendered > 0))[0, 0]
    error = ((rendered - truth) / truth.clamp_min(1e-9))[0, 0] / (2 * ERROR_RANGE) + 0.5
    panels.append(np.where(both.numpy()[..., None], colormaps["coolwarm"](error.clamp(0, 1).numpy())[..., :3], 1.0))
    return panels


def recorded(path: Path, key: str):
    """``key`` of the JSON file ``path`` a run folder records; a missing or damaged file or key stops, naming both."""
    try:
        return json.loads(path.read_text())[key]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise SystemExit(f"sparse_depth: {path}: no readable '{key}' ({type(exc).__name__}: {exc})") from exc


def run_rows(run: Path, noise: dict[str, float], seed: int) -> list[dict]:
    """One row per real view of reconstruction ``run``: its rendered depth's and the perturbed truth's statistics
    (and, under ``panels``, the figure's images of the view)."""
    data, views = Path(recorded(run / "data.json", "data")), recorded(run / "regime.json", "views")
    dataset = OLATDataset(data, "train")
    geometry = RenderedGeometry(run)
    generator = torch.Generator().manual_seed(seed)
    rows = []
    for view in views:
        truth = dataset.load_geometry_maps(view)[0].permute(2, 0, 1)[None].float()
        rendered = geometry.maps(dataset, view, None, (truth > 0).float()[0, 0, ..., None]).depth
        rendered = rendered.permute(2, 0, 1)[None].float()
        perturbed = perturb_depth(truth, generator, **noise)
        rows.append({"run": str(run), "view": view, "rendered": depth_stats(rendered, truth),
                     "perturbed": depth_stats(perturbed, truth), "panels": depth_panels(truth, rendered, perturbed)})
    return rows


def noise_setting(text: str) -> tuple[str, float]:
    key, sep, value = text.partition("=")
    if not sep or key not in ("share", "relative", "edge_px", "grid"):
        raise argparse.ArgumentTypeError(f"--noise {text!r}: give KEY=VALUE, KEY one of share, relative, edge_px, "
                                         "grid")
    return key, int(value) if key in ("edge_px", "grid") else float(value)


def mean_of(rows: list[dict], which: str) -> dict[str, float]:
    return {key: float(torch.tensor([r[which][key] for r in rows]).nanmean()) for key in STATS}


def markdown(rows: list[dict], noise: dict, note: str) -> str:
    lines = [f"Rendered depth of sparse reconstructions at their real views against the true depth, beside the true "
             f"depth perturbed by `perturb_depth({', '.join(f'{k}={v}' for k, v in noise.items())})`. {note}".strip(),
             "", "| run | views | depth | " + " | ".join(STATS) + " |", "|---|---|---|" + "---|" * len(STATS)]
    runs = dict.fromkeys(r["run"] for r in rows)
    for run in [*runs, "all"]:
        group = [r for r in rows if run in ("all", r["run"])]
        for which in ("rendered", "perturbed"):
            stats = mean_of(group, which)
            lines.append(f"| {Path(run).parent.parent.name}/{Path(run).parent.name} | {len(group)} | {which} | "
                         + " | ".join(f"{stats[k]:.3f}" for k in STATS) + " |" if run != "all" else
                         f"| **all** | {len(group)} | {which} | " + " | ".join(f"{stats[k]:.3f}" for k in STATS)
                         + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=Path, nargs="+", required=True, help="reconstruction run folders")
    parser.add_argument("--noise", type=noise_setting, nargs="*", default=[],
                        help="perturb_depth settings (share, relative, edge_px, grid)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tag", default="sparse_depth")
    parser.add_argument("--note", default="", help="a line for the Markdown (machine, date)")
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    missing = [str(run) for run in args.runs if not (run / "model.safetensors").is_file()]
    if missing:
        parser.error(f"--runs: not finished reconstruction runs (no model.safetensors): {', '.join(missing)}")
    noise = {"share": 1.0, "relative": 0.0, "edge_px": 0, **dict(args.noise)}
    try:
        rows = [row for run in args.runs for row in run_rows(run, noise, args.seed)]
    except DataError as exc:  # e.g. a capture without stored depth maps: the truth this compares with
        raise SystemExit(f"sparse_depth: {exc}") from exc
    args.results.mkdir(parents=True, exist_ok=True)
    save_image_grid(args.results / f"{args.tag}.png", [row.pop("panels") for row in rows],
                    row_labels=[f"{Path(r['run']).parent.parent.name[:12]} {Path(r['run']).parent.name} v{r['view']}"
                                for r in rows],
                    col_labels=["true depth", "rendered", "perturbed", f"rendered error (+-{ERROR_RANGE:.0%})"])
    (args.results / f"{args.tag}.json").write_text(json.dumps({"noise": noise, "rows": rows}, indent=1))
    table = markdown(rows, noise, args.note)
    (args.results / f"{args.tag}.md").write_text(table)
    print(table)


if __name__ == "__main__":
    main()
