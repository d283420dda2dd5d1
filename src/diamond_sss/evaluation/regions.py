"""Where the error is: a test image's pixels split into regions from its true geometry and lighting.

Regions, disjoint and covering the frame, from the ground truth of one image (mask ``m``, stored depth and
world normals ``n``, the light position ``p``; ``x`` the surface point of a pixel, ``w_l = normalize(p - x)``):

* ``background``: outside the mask dilated by one pixel;
* ``silhouette``: the two-pixel band across the mask's boundary (dilated minus eroded mask), and interior
  pixels without a stored depth;
* ``back_lit``: interior pixels with ``n . w_l <= 0``: light reaches them only through the material;
* ``shadow``: interior, ``n . w_l > 0``, luminance below ``SHADOW_FRACTION`` of the median of those pixels
  (cast shadows of the object on itself);
* ``highlight``: interior, ``n . w_l > 0``, luminance above that set's ``HIGHLIGHT_QUANTILE``;
* ``lit``: the other front-lit interior pixels.

Errors are squared differences of sRGB values in ``[0, 1]``, as the metrics (:mod:`.metrics`) compute them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm.auto import tqdm

from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.evaluation.evaluate import render_observation
from diamond_sss.evaluation.figures import save_image_grid, to_display
from diamond_sss.scene.model import RelightableScene
from diamond_sss.shading.deferred import backproject_depth

REGIONS = ("background", "silhouette", "back_lit", "shadow", "highlight", "lit")
REGION_COLORS = {"background": (0.0, 0.0, 0.0), "silhouette": (1.0, 1.0, 0.0), "back_lit": (0.2, 0.4, 1.0),
                 "shadow": (0.5, 0.0, 0.6), "highlight": (1.0, 1.0, 1.0), "lit": (1.0, 0.5, 0.1)}
SHADOW_FRACTION = 0.25
HIGHLIGHT_QUANTILE = 0.95
REC709_LUMA = (0.2126, 0.7152, 0.0722)


def _binary_dilate(mask: Tensor) -> Tensor:
    """3x3 dilation of a boolean ``[H, W]`` mask."""
    return F.max_pool2d(mask[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0.5


def error_regions(mask: Tensor, depth: Tensor, normals: Tensor, w2c: Tensor, K: Tensor, light_position: Tensor,
                  rgb: Tensor) -> dict[str, Tensor]:
    """Boolean ``[H, W]`` maps of :data:`REGIONS` for one image (see the module docstring).

    ``mask [H,W,1]`` in [0,1], ``depth [H,W,1]`` camera z (0 = background), ``normals [H,W,3]`` world,
    ``w2c [4,4]`` OpenCV, ``K [3,3]``, ``light_position [3]`` world, ``rgb [H,W,3]`` linear ground truth.
    """
    foreground = mask[..., 0] > 0.5
    dilated = _binary_dilate(foreground)
    eroded = ~_binary_dilate(~foreground)
    interior = eroded & (depth[..., 0] > 0)
    points = backproject_depth(depth[None], w2c[None], K[None])[0]
    to_light = F.normalize(light_position.to(points) - points, dim=-1)
    cosine = (F.normalize(normals, dim=-1) * to_light).sum(-1)
    front = interior & (cosine > 0)
    luminance = (rgb * torch.tensor(REC709_LUMA, dtype=rgb.dtype, device=rgb.device)).sum(-1)
    shadow = torch.zeros_like(front)
    highlight = torch.zeros_like(front)
    if bool(front.any()):
        values = luminance[front]
        shadow = front & (luminance < SHADOW_FRACTION * values.median())
        highlight = front & ~shadow & (luminance > torch.quantile(values, HIGHLIGHT_QUANTILE))
    silhouette = (dilated & ~eroded) | (eroded & ~interior)
    return {"background": ~dilated, "silhouette": silhouette, "back_lit": interior & ~front, "shadow": shadow,
            "highlight": highlight, "lit": front & ~shadow & ~highlight}


@dataclass
class RegionErrors:
    """Squared-error sums and pixel counts per region, accumulated over images."""

    squared_error: dict[str, float] = field(default_factory=lambda: dict.fromkeys(REGIONS, 0.0))
    pixels: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REGIONS, 0))

    def add(self, pred_srgb: Tensor, target_srgb: Tensor, regions: dict[str, Tensor]) -> None:
        """Accumulate one image pair ``[H,W,3]`` over its region maps."""
        error = ((pred_srgb - target_srgb) ** 2).sum(-1)
        for name in REGIONS:
            self.squared_error[name] += float(error[regions[name]].sum())
            self.pixels[name] += int(regions[name].sum())

    def summary(self) -> dict[str, dict[str, float]]:
        """Per region: ``pixel_share``, ``error_share`` (of the total squared error) and ``psnr`` (dB)."""
        total_error = sum(self.squared_error.values()) or 1.0
        total_pixels = sum(self.pixels.values()) or 1
        out = {}
        for name in REGIONS:
            count, error = self.pixels[name], self.squared_error[name]
            mse = error / (3 * count) if count else float("nan")
            out[name] = {"pixel_share": count / total_pixels, "error_share": error / total_error,
                         "psnr": float("nan") if not count else (100.0 if mse <= 1e-10 else -10 * math.log10(mse))}
        return out


def _image_regions(dataset: OLATDataset, index: int) -> tuple[dict[str, Tensor], Tensor]:
    sample = dataset.load(index)
    camera, light = dataset.cameras[sample.view], dataset.lights[sample.light]
    depth, normals = dataset.load_geometry_maps(sample.view)
    regions = error_regions(sample.mask, depth, normals, camera.w2c, camera.K, light.position, sample.rgb)
    return regions, sample.rgb


@torch.no_grad()
def region_errors(scene: RelightableScene, dataset: OLATDataset, *, max_images: int | None = None,
                  show_progress: bool = False) -> RegionErrors:
    """Render every observation of ``dataset`` whose view has depth and normal maps; errors per region."""
    device = next(scene.parameters()).device
    errors = RegionErrors()
    count = len(dataset) if max_images is None else min(max_images, len(dataset))
    indices = [i for i in range(count) if dataset.has_geometry_maps(dataset.observations[i].view)]
    if not indices:
        raise ValueError(f"{dataset.json_path}: no view has depth/normal maps: the error regions need them")
    for index in tqdm(indices, desc="regions", disable=not show_progress, dynamic_ncols=True):
        regions, rgb = _image_regions(dataset, index)
        pred = render_observation(scene, dataset, index, device).radiance[0].float().cpu()
        errors.add(linear_to_srgb(pred), linear_to_srgb(rgb), regions)
    return errors


def region_label_image(regions: dict[str, Tensor]) -> np.ndarray:
    """An ``[H,W,3]`` display image colouring each pixel by its region (:data:`REGION_COLORS`)."""
    first = next(iter(regions.values()))
    image = np.zeros((*first.shape, 3), dtype=np.float32)
    for name in REGIONS:
        image[regions[name].cpu().numpy()] = REGION_COLORS[name]
    return image


@torch.no_grad()
def save_region_figure(path: Path, scene: RelightableScene, dataset: OLATDataset, indices: Sequence[int],
                       title: str | None = None) -> Path:
    """Rows of GT | render | |error| x4 (sRGB) | regions, for the given observations."""
    device = next(scene.parameters()).device
    rows, labels = [], []
    for index in indices:
        regions, rgb = _image_regions(dataset, index)
        pred = render_observation(scene, dataset, index, device).radiance[0].cpu()
        gt_display, pred_display = to_display(rgb), to_display(pred)
        rows.append([gt_display, pred_display, (abs(gt_display - pred_display) * 4.0).clip(0.0, 1.0),
                     region_label_image(regions)])
        observation = dataset.observations[index]
        labels.append(f"view {observation.view}, light {observation.light}")
    legend = ", ".join(f"{name}" for name in REGIONS[1:])
    return save_image_grid(path, rows, row_labels=labels,
                           col_labels=["ground truth", "render", "|error| x4", "regions"],
                           title=title or f"regions: {legend}")
