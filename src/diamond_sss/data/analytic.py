"""Small analytic OLAT captures (a ray-cast Lambertian sphere) in both JSON variants, for tests and benchmarks.

No renderer needed: every image is exact, so loaders, regimes and training can be checked in seconds.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from diamond_sss.data.conventions import (
    camera_centers,
    intrinsics_from_fov,
    linear_to_srgb,
    look_at_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    pixel_ray_directions,
)
from diamond_sss.data.images import write_png

SPHERE_RADIUS = 0.5
FOV_X = math.radians(40.0)


def fibonacci_sphere(count: int, radius: float, offset: float = 0.0) -> np.ndarray:
    """``count`` points spread on a sphere (golden-angle spiral), rotated by ``offset`` radians."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i + offset
    return radius * np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def render_sphere(c2w: np.ndarray, light: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast a Lambertian sphere at the origin: linear RGB ``[H,W,3]`` and alpha ``[H,W]`` (0/1)."""
    w2c = opengl_c2w_to_opencv_w2c(torch.from_numpy(c2w))
    K = intrinsics_from_fov(FOV_X, size, size).double()
    dirs = pixel_ray_directions(w2c, K, size, size).numpy()
    origin = camera_centers(w2c).numpy()
    b = (dirs * origin).sum(-1)
    disc = b * b - (origin @ origin - SPHERE_RADIUS**2)
    hit = disc > 0
    t = -b - np.sqrt(np.clip(disc, 0, None))
    points = origin + t[..., None] * dirs
    normals = points / SPHERE_RADIUS
    to_light = light - points
    to_light /= np.linalg.norm(to_light, axis=-1, keepdims=True)
    shade = np.clip((normals * to_light).sum(-1), 0, None) * 0.8 + 0.05
    rgb = np.stack([shade, 0.8 * shade, 0.6 * shade], axis=-1) * hit[..., None]
    return rgb, hit.astype(np.float64)


def make_capture(root: Path, *, views: int = 6, lights: int = 4, size: int = 16, variant: str = "sss3dgs",
                 split: str = "train", camera_offset: float = 0.0, light_offset: float = 0.0,
                 bit_depth: int = 8) -> dict:
    """Write ``transforms_<split>.json`` and RGBA PNGs of a full ``views x lights`` lattice; return the truth."""
    root.mkdir(parents=True, exist_ok=True)
    cam_pos = fibonacci_sphere(views, 3.0, camera_offset)
    light_pos = fibonacci_sphere(lights, 4.0, light_offset)
    frames = []
    truth = {"c2w": [], "lights": light_pos, "images": []}
    for v in range(views):
        c2w = look_at_opengl_c2w(torch.from_numpy(cam_pos[v]), torch.zeros(3)).numpy()
        truth["c2w"].append(c2w)
        paths = []
        for light_index in range(lights):
            rgb, alpha = render_sphere(c2w, light_pos[light_index], size)
            srgb = linear_to_srgb(torch.from_numpy(rgb)).numpy()
            rgba = np.concatenate([srgb, alpha[..., None]], axis=-1)
            rel = f"{split}/v{v:03d}_l{light_index:03d}.png"
            if bit_depth == 16:
                write_png(root / rel, (rgba * 65535 + 0.5).astype(np.uint16))
            else:
                write_png(root / rel, (rgba * 255 + 0.5).astype(np.uint8))
            paths.append(rel)
            truth["images"].append((v, light_index, rel, rgb))
            if variant == "per-image":
                frames.append({"file_path": rel, "transform_matrix": c2w.tolist(),
                               "pl_pos": light_pos[light_index].tolist(), "pl_intensity": [1.0, 1.0, 1.0]})
        if variant == "sss3dgs":
            frames.append({"transform_matrix": c2w.tolist(), "file_paths": paths,
                           "light_positions": [light_pos[k].tolist() for k in range(lights)],
                           "light_intensities": [[1.0, 1.0, 1.0]] * lights})
    (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": FOV_X, "frames": frames}))
    return truth


def make_capture_with_test_split(root: Path, *, views: int = 6, lights: int = 3, size: int = 16,
                                 test_views: int = 2, test_lights: int = 2, camera_offset: float = 0.0) -> Path:
    """:func:`make_capture`'s ``views x lights`` training lattice and a ``test_views x test_lights`` test split of
    novel cameras and novel lights (Fibonacci spheres turned by 0.4 and 0.9); returns ``root``."""
    make_capture(root, views=views, lights=lights, size=size, camera_offset=camera_offset)
    make_capture(root, views=test_views, lights=test_lights, size=size, split="test", camera_offset=0.4,
                 light_offset=0.9)
    return root
