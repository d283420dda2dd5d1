"""Run-level jobs behind the CLI: evaluate a trained run folder, render it (data cameras or an orbit)."""

from __future__ import annotations

import importlib.util
import math
from collections.abc import Sequence
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from diamond_sss.data.conventions import intrinsics_matrix, look_at_opengl_c2w, opengl_c2w_to_opencv_w2c
from diamond_sss.data.dataset import Light, OLATDataset
from diamond_sss.data.images import to_srgb8, write_png
from diamond_sss.evaluation.evaluate import (
    evaluate_scene,
    save_comparison_figure,
    save_decomposition_figure,
    write_evaluation,
)
from diamond_sss.runs.folder import load_scene
from diamond_sss.utils.device import resolve_device
from diamond_sss.utils.io import atomic_write_bytes, read_json


def evaluate_run(run: Path, data: Path, *, split: str = "test", lpips_weights: str | None = None,
                 max_images: int | None = None, figures: int = 4, device: str = "auto",
                 show_progress: bool = True) -> dict:
    """Evaluate a run on ``split``; writes ``<run>/eval_<split>/`` and returns the summary."""
    scene, cfg = load_scene(run, resolve_device(device))
    dataset = OLATDataset(data, split, downscale=cfg.runtime.downscale)
    evaluation = evaluate_scene(scene, dataset, lpips_weights=lpips_weights, max_images=max_images,
                                show_progress=show_progress)
    out_dir = Path(run) / f"eval_{split}"
    extra = {"split": split, "data": str(Path(data).resolve())}
    write_evaluation(out_dir, evaluation, extra)
    if figures > 0:
        count = min(figures, len(dataset))
        picks = [round(i * (len(dataset) - 1) / max(1, count - 1)) for i in range(count)]
        save_comparison_figure(out_dir / "comparison.png", scene, dataset, picks, title=f"{Path(run).name} [{split}]")
        save_decomposition_figure(out_dir / "decomposition.png", scene, dataset, picks[0])
    return {**evaluation.summary, **extra}


def orbit_cameras(center: torch.Tensor, radius: float, frames: int, elevation_deg: float) -> torch.Tensor:
    """``[F,4,4]`` OpenCV w2c of cameras circling ``center`` (world Z up) at ``radius``."""
    elevation = math.radians(elevation_deg)
    mats = []
    for k in range(frames):
        azimuth = 2.0 * math.pi * k / frames
        eye = center.double() + radius * torch.tensor([math.cos(elevation) * math.cos(azimuth),
                                                       math.cos(elevation) * math.sin(azimuth),
                                                       math.sin(elevation)], dtype=torch.float64)
        mats.append(opengl_c2w_to_opencv_w2c(look_at_opengl_c2w(eye, center.double())).float())
    return torch.stack(mats)


def check_animation_path(path: Path) -> str:
    """The suffix of an orbit animation file (``.gif`` or ``.mp4``); MP4 needs imageio-ffmpeg."""
    suffix = Path(path).suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"--video {path}: expected a file name ending in .gif or .mp4")
    if suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise ValueError(f"--video {path}: writing MP4 needs imageio-ffmpeg (pip install 'diamond-sss[video]'); "
                         "a .gif name needs nothing more")
    return suffix


def write_animation(path: Path, frames: Sequence[np.ndarray], frame_ms: int = 80) -> Path:
    """Frames ``[H,W,3]`` uint8 as a looping GIF or, for a ``.mp4`` name, an H.264 MP4 (sides padded to even)."""
    suffix = check_animation_path(path)
    stack = np.stack(frames)
    if suffix == ".gif":
        return atomic_write_bytes(path, iio.imwrite("<bytes>", stack, extension=".gif", duration=frame_ms, loop=0))
    pad = ((0, 0), (0, stack.shape[1] % 2), (0, stack.shape[2] % 2), (0, 0))
    video = iio.imwrite("<bytes>", np.pad(stack, pad, mode="edge"), extension=".mp4", plugin="FFMPEG",
                        fps=1000.0 / frame_ms, codec="libx264", macro_block_size=1)
    return atomic_write_bytes(path, video)


@torch.no_grad()
def render_run(run: Path, out: Path, *, data: Path | None = None, split: str = "test",
               views: Sequence[int] = (), orbit: int = 0, orbit_elevation_deg: float = 20.0,
               lights: Sequence[float] = (), light_intensity: float = 1.0, overrides: dict | None = None,
               size: int | None = None, device: str = "auto", video: Path = Path("orbit.gif")) -> list[Path]:
    """Render data cameras or an orbit under given lights (summed, each of RGB intensity ``light_intensity``;
    default: each data view's first light at the capture's intensity, an orbit's the data's first image's) with
    material overrides: PNGs, and for an orbit (square frames centred on the object) the animation ``out / video``
    (GIF, or MP4 for a ``.mp4`` name)."""
    if orbit > 0:
        check_animation_path(video)
    run = Path(run)
    scene, cfg = load_scene(run, resolve_device(device))
    dev = next(scene.parameters()).device
    if data is None:
        data = Path(read_json(run / "data.json")["data"])
    dataset = OLATDataset(data, split, downscale=cfg.runtime.downscale)
    if len(lights) % 3 != 0:
        raise ValueError(f"--light expects x y z triples, got {len(lights)} numbers")
    given = [Light(position=torch.tensor(lights[i:i + 3], dtype=torch.float32),
                   intensity=torch.full((3,), float(light_intensity))) for i in range(0, len(lights), 3)]
    if orbit > 0:
        width = height = size or dataset.width
        K = dataset.intrinsics[0]
        scale = width / dataset.width
        K = intrinsics_matrix(float(K[0, 0]) * scale, float(K[1, 1]) * scale, 0.5 * width, 0.5 * height)
        bounds = dataset.bounds
        distance = float(dataset.camera_centers.sub(bounds.center).norm(dim=-1).mean())
        cameras = [(w2c, K, given or [dataset.first_light()])
                   for w2c in orbit_cameras(bounds.center, distance, orbit, orbit_elevation_deg)]
    else:
        chosen = list(views) or list(range(dataset.num_views))
        for view in chosen:
            if not 0 <= view < dataset.num_views:
                raise ValueError(f"--views: view {view} is not in {data} [{split}] (0..{dataset.num_views - 1})")
        cameras = [(dataset.cameras[v].w2c, dataset.cameras[v].K, given or [dataset.first_light(v)]) for v in chosen]
        width, height = dataset.width, dataset.height
    out = Path(out)
    written, frames = [], []
    for k, (w2c, K, frame_lights) in enumerate(cameras):
        radiance = torch.zeros(height, width, 3, device=dev)
        alpha = torch.zeros(height, width, 1, device=dev)
        for light in frame_lights:
            render = scene.render(w2c[None].to(dev), K[None].to(dev), width, height, light.position[None].to(dev),
                                  light.intensity[None].to(dev), overrides=overrides)
            radiance += render.radiance[0]
            alpha = render.gbuffer.alpha[0]
        image = to_srgb8(radiance.cpu(), alpha.cpu())
        written.append(write_png(out / f"frame_{k:04d}.png", image))
        frames.append(image[..., :3])
    if orbit > 0:
        written.append(write_animation(out / video, frames))
    return written
