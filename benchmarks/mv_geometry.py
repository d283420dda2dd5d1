"""Geometry of trained runs against a capture's true depth maps (issue 58: what the multi-view losses change).

For every view of the split that has a stored depth map, the run's scene is rendered (depth and alpha only) and
compared with the true camera-space depth ``D*`` and the true mask ``M = D* > 0``:

* ``depth_mae``: mean ``|D - D*|`` in scene units over pixels inside both ``M`` and the rendered silhouette
  (``alpha >= 0.5``), ``D`` the alpha-normalised expected depth the multi-view losses use;
* ``depth_mae_rel``: the same divided by the scene's ``far - near`` (the losses' normalised units);
* ``mask_iou``: ``|M & A| / |M | A|`` with ``A = alpha >= 0.5``;
* ``leak``: fraction of the rendered silhouette outside ``M`` (boundary bleeding / floaters);
* ``depth_bias``: mean signed ``D - D*`` (positive: the expected depth lies behind the true surface);
* ``interior_depth_bias``: the same over the pixels of ``M`` more than ``RIM_PX`` pixels inside its outline (a bias
  there moves the surface itself, not only the outline's pixels);
* ``fringe_alpha``: mean rendered alpha over the pixels within ``FRINGE_PX`` outside ``M`` (a soft halo round the
  object, which costs the background's PSNR); either is NaN, with a line saying why, where it has no pixel;
* ``median_depth_mae`` / ``median_depth_bias``: the same for the depth where the transmittance crosses 0.5,
  ``D_0.5``: the Gaussians with centre depth below ``t`` are rendered for ``SWEEP`` thresholds ``t`` in
  ``[near, far]`` and ``D_0.5`` is interpolated linearly where their alpha crosses 0.5.

    python benchmarks/mv_geometry.py outputs/mv/on_s0 outputs/mv/off_s0 --data src/diamond_sss/assets/data/demo
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from scipy import ndimage
from torch import Tensor

from diamond_sss.data.conventions import world_to_camera
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.rendering import rasterize
from diamond_sss.runs.folder import load_scene
from diamond_sss.scene.model import RelightableScene

SWEEP = 16
RIM_PX = 2.0
FRINGE_PX = 1.5


def median_depth(scene: RelightableScene, w2c: Tensor, K: Tensor, width: int, height: int, near: float,
                 far: float) -> Tensor:
    """``D_0.5 [H,W]``: depth at which the alpha of the Gaussians in front first reaches 0.5 (NaN where never)."""
    g = scene.gaussians
    z = world_to_camera(g.means, w2c)[:, 2]
    ones = torch.ones(g.num_gaussians, 1)
    thresholds = torch.linspace(near, far, SWEEP)
    alphas = torch.stack([
        rasterize(g.means, g.quats, g.scales, g.opacities * (z < t), ones, w2c[None], K[None], width, height,
                  backend="cpu").alpha[0, ..., 0]
        for t in thresholds
    ])
    crossed = alphas >= 0.5
    first = crossed.to(torch.int64).argmax(0)
    before = (first - 1).clamp_min(0)
    a0, a1 = alphas.gather(0, before[None])[0], alphas.gather(0, first[None])[0]
    t0, t1 = thresholds[before], thresholds[first]
    frac = ((0.5 - a0) / (a1 - a0).clamp_min(1e-6)).clamp(0.0, 1.0)
    depth = torch.where(first > 0, t0 + frac * (t1 - t0), t1)
    return torch.where(crossed.any(0), depth, torch.full_like(depth, float("nan")))


def _mean_or_nan(total: float, count: int, why_empty: str) -> float:
    """``total / count``, or NaN with ``why_empty`` on stderr when no pixel was counted."""
    if count:
        return total / count
    print(f"mv_geometry: {why_empty}; reported as NaN", file=sys.stderr)
    return float("nan")


@torch.no_grad()
def run_geometry(run: Path, dataset: OLATDataset) -> dict[str, float]:
    """Depth error, mask IoU and leak of one run's scene on every view of ``dataset`` with a depth map."""
    scene, _ = load_scene(run)
    bounds = dataset.bounds
    views = [v for v in range(len(dataset.cameras)) if dataset.has_geometry_maps(v)]
    if not views:
        raise ValueError(f"{dataset.json_path}: no view has a depth map (render the capture with synth --maps)")
    error_sum, bias_sum, error_count, inter, union, leak, rendered = 0.0, 0.0, 0, 0, 0, 0, 0
    median_sum, median_bias, median_count = 0.0, 0.0, 0
    interior_bias, interior_count, fringe_sum, fringe_count = 0.0, 0, 0.0, 0
    for view in views:
        camera = dataset.cameras[view]
        true_depth = dataset.load_geometry_maps(view)[0][..., 0]
        out = scene.render_geometry(camera.w2c[None], camera.K[None], camera.width, camera.height)
        depth, alpha = out.depth[0, ..., 0], out.alpha[0, ..., 0]
        truth, covered = true_depth > 0, alpha >= 0.5
        both = truth & covered
        error_sum += float((depth - true_depth)[both].abs().sum())
        bias_sum += float((depth - true_depth)[both].sum())
        error_count += int(both.sum())
        inside = torch.from_numpy(ndimage.distance_transform_edt(truth.numpy()) > RIM_PX) & covered
        interior_bias += float((depth - true_depth)[inside].sum())
        interior_count += int(inside.sum())
        outside = ndimage.distance_transform_edt(~truth.numpy())
        fringe = torch.from_numpy((outside > 0) & (outside <= FRINGE_PX))
        fringe_sum += float(alpha[fringe].sum())
        fringe_count += int(fringe.sum())
        surface = median_depth(scene, camera.w2c, camera.K, camera.width, camera.height, bounds.near, bounds.far)
        hit = truth & torch.isfinite(surface)
        median_sum += float((surface - true_depth)[hit].abs().sum())
        median_bias += float((surface - true_depth)[hit].sum())
        median_count += int(hit.sum())
        inter += int(both.sum())
        union += int((truth | covered).sum())
        leak += int((covered & ~truth).sum())
        rendered += int(covered.sum())
    mae = error_sum / max(error_count, 1)
    return {"depth_mae": mae, "depth_mae_rel": mae / (bounds.far - bounds.near),
            "depth_bias": bias_sum / max(error_count, 1),
            "interior_depth_bias": _mean_or_nan(interior_bias, interior_count, f"{run}: no covered pixel lies more than "
                                                f"{RIM_PX:g} px inside the true outline"),
            "fringe_alpha": _mean_or_nan(fringe_sum, fringe_count, f"{run}: no pixel lies within {FRINGE_PX:g} px "
                                         "outside the true outline"), "median_depth_mae": median_sum / max(median_count, 1),
            "median_depth_bias": median_bias / max(median_count, 1), "mask_iou": inter / max(union, 1),
            "leak": leak / max(rendered, 1), "views": len(views)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", type=Path, nargs="+", help="finished run folders")
    parser.add_argument("--data", type=Path, default=None, help="data folder (default: the embedded demo)")
    parser.add_argument("--split", default="test")
    args = parser.parse_args()
    dataset = OLATDataset(args.data or embedded_dataset(), args.split)
    rows = {str(run): run_geometry(run, dataset) for run in args.runs}
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
