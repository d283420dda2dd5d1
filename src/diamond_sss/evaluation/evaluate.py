"""Score a trained scene on a split (novel views under novel lights): metrics JSON, per-image CSV, figures."""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from tqdm.auto import tqdm

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.evaluation.figures import save_image_grid, to_display
from diamond_sss.evaluation.metrics import ImageMetrics, image_metrics, mean_metrics
from diamond_sss.losses.lpips import load_lpips
from diamond_sss.scene.model import RelightableScene, SceneRender
from diamond_sss.utils.io import atomic_write_json, atomic_write_text

DECOMPOSITION = ("base_color", "normal", "roughness", "metallic", "subsurface", "diffuse", "specular",
                 "residual", "incident", "visibility")


@dataclass
class Evaluation:
    """Mean metrics (``psnr``, ``ssim``, ``lpips``, ``masked_psnr``, ``mask_iou``, ``images``) and per image."""

    summary: dict
    rows: list[tuple[int, int, ImageMetrics]]


@torch.no_grad()
def render_observation(scene: RelightableScene, dataset: OLATDataset, index: int,
                       device: torch.device) -> SceneRender:
    """Render the (view, light) of observation ``index`` of ``dataset``."""
    obs = dataset.observations[index]
    camera = dataset.cameras[obs.view]
    light = dataset.lights[obs.light]
    return scene.render(camera.w2c[None].to(device), camera.K[None].to(device), camera.width, camera.height,
                        light.position[None].to(device), light.intensity[None].to(device))


@torch.no_grad()
def evaluate_scene(scene: RelightableScene, dataset: OLATDataset, *, lpips_weights: str | None = None,
                   max_images: int | None = None, show_progress: bool = True) -> Evaluation:
    """Render every observation of ``dataset`` and compare with its image (sRGB, full frame, black)."""
    device = next(scene.parameters()).device
    lpips_model = load_lpips(lpips_weights)
    if lpips_model is not None:
        lpips_model = lpips_model.to(device)
    count = len(dataset) if max_images is None else min(max_images, len(dataset))
    rows = []
    for index in tqdm(range(count), desc="eval", disable=not show_progress, dynamic_ncols=True):
        sample = dataset.load(index)
        render = render_observation(scene, dataset, index, device)
        metrics = image_metrics(render.radiance[0], sample.rgb, render.gbuffer.alpha[0], sample.mask, lpips_model)
        rows.append((sample.view, sample.light, metrics))
    return Evaluation(summary=mean_metrics([m for _, _, m in rows]), rows=rows)


def write_evaluation(out_dir: Path, evaluation: Evaluation, extra: dict | None = None) -> Path:
    """``metrics.json`` (means + ``extra``) and ``per_image.csv`` in ``out_dir``; returns the JSON path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["view", "light", "psnr", "ssim", "lpips", "masked_psnr", "mask_iou"])
    for view, light, m in evaluation.rows:
        writer.writerow([view, light, f"{m.psnr:.4f}", f"{m.ssim:.5f}", "" if m.lpips is None else f"{m.lpips:.5f}",
                         f"{m.masked_psnr:.4f}", f"{m.mask_iou:.5f}"])
    atomic_write_text(out_dir / "per_image.csv", buffer.getvalue())
    return atomic_write_json(out_dir / "metrics.json", {**evaluation.summary, **(extra or {})})


@torch.no_grad()
def save_comparison_figure(path: Path, scene: RelightableScene, dataset: OLATDataset, indices: list[int],
                           title: str | None = None) -> Path:
    """Rows of GT | render | |error| x4 for the given test observations."""
    device = next(scene.parameters()).device
    rows, labels = [], []
    for index in indices:
        sample = dataset.load(index)
        render = render_observation(scene, dataset, index, device)
        pred = render.radiance[0].cpu()
        gt_display, pred_display = to_display(sample.rgb), to_display(pred)
        error = (abs(gt_display - pred_display) * 4.0).clip(0.0, 1.0)
        rows.append([gt_display, pred_display, error])
        labels.append(f"view {sample.view}, light {sample.light}")
    return save_image_grid(path, rows, row_labels=labels, col_labels=["ground truth", "render", "|error| x4"],
                           title=title)


@torch.no_grad()
def decomposition_maps(render: SceneRender) -> dict[str, tuple[Tensor, bool]]:
    """The :data:`DECOMPOSITION` maps of a render, ``name -> (image [B,H,W,C], is linear radiance)``."""
    gb, sh = render.gbuffer, render.shading
    return {
        "base_color": (gb.base_color, False), "normal": ((gb.normal * 0.5 + 0.5) * gb.alpha, False),
        "roughness": (gb.roughness, False), "metallic": (gb.metallic, False),
        "subsurface": (gb.subsurface, False), "diffuse": (sh.diffuse, True), "specular": (sh.specular, True),
        "residual": (sh.residual, True), "incident": (gb.incident.clamp(0, 1), False),
        "visibility": (gb.visibility, False),
    }


def save_decomposition_figure(path: Path, scene: RelightableScene, dataset: OLATDataset, index: int) -> Path:
    """The G-buffer and shading terms of one observation: base colour, normal, ..., visibility."""
    device = next(scene.parameters()).device
    render = render_observation(scene, dataset, index, device)
    maps = decomposition_maps(render)
    images = [to_display(maps[name][0][0], linear=maps[name][1]) for name in DECOMPOSITION]
    radiance = to_display(render.radiance[0])
    return save_image_grid(path, [[radiance] + images[:5], images[5:]],
                           cell_labels=[["render", *DECOMPOSITION[:5]], list(DECOMPOSITION[5:])],
                           title=f"decomposition: view {dataset.observations[index].view}, "
                                 f"light {dataset.observations[index].light}")
