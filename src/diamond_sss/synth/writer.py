"""Atomic writers for the NeRF-synthetic / SSS-3DGS OLAT format.

Every file is written to a temporary sibling and moved into place with ``os.replace``, so a reader never
sees half-written JSON, PNG or NPY files. Images are 8-bit RGBA PNGs: RGB is the sRGB encoding of the
exposed, alpha-premultiplied linear radiance (black background), alpha the object coverage.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.utils.io import atomic_write_bytes


def write_json(path: Path, payload: dict) -> None:
    """Atomically write ``payload`` as indented JSON."""
    atomic_write_bytes(path, (json.dumps(payload, indent=2) + "\n").encode())


def write_npy(path: Path, array: np.ndarray) -> None:
    """Atomically write a float32 ``.npy`` (readable with ``allow_pickle=False``)."""
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array, dtype=np.float32), allow_pickle=False)
    atomic_write_bytes(path, buffer.getvalue())


def encode_rgba8(linear_rgba: np.ndarray, exposure: float) -> np.ndarray:
    """``[H,W,4]`` linear premultiplied RGBA -> uint8 RGBA: ``srgb(clip(exposure * rgb))``, ``clip(alpha)``."""
    if linear_rgba.ndim != 3 or linear_rgba.shape[-1] != 4:
        raise ValueError(f"expected an [H,W,4] RGBA image, got shape {linear_rgba.shape}")
    rgb = linear_to_srgb(torch.from_numpy(np.ascontiguousarray(linear_rgba[..., :3] * exposure))).numpy()
    alpha = np.clip(linear_rgba[..., 3:], 0.0, 1.0)
    return np.round(np.concatenate([rgb, alpha], axis=-1) * 255.0).astype(np.uint8)


def write_png(path: Path, rgba8: np.ndarray) -> None:
    """Atomically write an ``[H,W,4]`` uint8 RGBA PNG."""
    if rgba8.dtype != np.uint8 or rgba8.ndim != 3 or rgba8.shape[-1] != 4:
        raise ValueError(f"expected an [H,W,4] uint8 image, got {rgba8.dtype} {rgba8.shape}")
    atomic_write_bytes(path, iio.imwrite("<bytes>", rgba8, extension=".png"))


@dataclass
class FrameRecord:
    """One camera view of a split: its pose and the images taken under each light."""

    c2w: np.ndarray
    file_paths: list[str] = field(default_factory=list)
    light_positions: list[list[float]] = field(default_factory=list)
    light_intensities: list[list[float]] = field(default_factory=list)
    depth_path: str | None = None
    normal_path: str | None = None

    def to_json(self) -> dict:
        out: dict = {
            "transform_matrix": np.asarray(self.c2w, dtype=np.float64).tolist(),
            "file_paths": list(self.file_paths),
            "light_positions": [list(map(float, p)) for p in self.light_positions],
            "light_intensities": [list(map(float, i)) for i in self.light_intensities],
        }
        if self.depth_path is not None:
            out["depth_path"] = self.depth_path
        if self.normal_path is not None:
            out["normal_path"] = self.normal_path
        return out


def transforms_payload(camera_angle_x: float, width: int, height: int, frames: list[FrameRecord]) -> dict:
    """The ``transforms_<split>.json`` dictionary."""
    return {
        "premultiplied_alpha": True,
        "camera_angle_x": float(camera_angle_x),
        "w": int(width),
        "h": int(height),
        "frames": [frame.to_json() for frame in frames],
    }


def write_transforms(
    folder: Path, split: str, camera_angle_x: float, width: int, height: int, frames: list[FrameRecord]
) -> Path:
    """Atomically write ``folder/transforms_<split>.json``; returns its path."""
    path = Path(folder) / f"transforms_{split}.json"
    write_json(path, transforms_payload(camera_angle_x, width, height, frames))
    return path
