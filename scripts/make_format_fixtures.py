"""Write the tiny data-format fixtures of tests/fixtures/formats (one folder per variant of the OLAT format).

    python scripts/make_format_fixtures.py [--out tests/fixtures/formats]

Variants (2 views x 3 lights of a flat-shaded square, RGBA PNGs):

* ``object_full``: SSS-3DGS release style at full size (8 px stands in for 800 px): one frame per view
  with per-frame ``width``, ``height``, ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``file_paths`` without
  extension, ``light_positions`` and ``light_intensities``; ``exclude_list.txt`` names two images (one
  with ``.png``, one without; the first is not even on disk).
* ``object_small``: the same capture at small size (4 px stands in for 256 px): the same JSON (intrinsics
  stated for the full size), images half the size.
* ``split_variants``: one object folder holding both sizes as splits, ``transforms_train_full.json`` with
  images in ``train_full/`` and ``transforms_train_small.json`` with images in ``train_small/``.
* ``nrhints``: per-image (NRHints) style: one frame per image with ``file_path`` (``./`` prefix, no
  extension), ``transform_matrix``, ``pl_pos`` and ``pl_intensity``; top-level ``camera_angle_x``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from diamond_sss.data.images import write_png
from diamond_sss.utils.io import atomic_write_text

FULL, SMALL = 8, 4
VIEWS, LIGHTS = 2, 3
EXCLUDED = ("r_001_l_002.png", "train/r_000_l_001")


def camera_to_world(view: int) -> list[list[float]]:
    """A camera on the +y side (view 0) or +x side (view 1) at distance 4, looking at the origin (OpenGL)."""
    angle = view * math.pi / 2
    eye = np.array([4 * math.sin(angle), -4 * math.cos(angle), 0.0])
    forward = -eye / np.linalg.norm(eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -forward, eye
    return np.round(c2w, 12).tolist()


def light_position(light: int) -> list[float]:
    angle = 2 * math.pi * light / LIGHTS
    return [round(5 * math.cos(angle), 9), round(5 * math.sin(angle), 9), 2.0]


def image(view: int, light: int, size: int) -> np.ndarray:
    """RGBA uint8: a grey level per (view, light) on the centre half of the frame, transparent elsewhere."""
    rgba = np.zeros((size, size, 4), np.uint8)
    inner = slice(size // 4, size - size // 4)
    rgba[inner, inner, :3] = 40 + 60 * view + 30 * light
    rgba[inner, inner, 3] = 255
    return rgba


def name(view: int, light: int) -> str:
    return f"r_{view:03d}_l_{light:03d}"


def sss3dgs_frames(folder: str) -> list[dict]:
    """One frame per view: per-frame size and pixel intrinsics stated for the full size."""
    frames = []
    for view in range(VIEWS):
        lights = range(LIGHTS)
        frames.append({
            "transform_matrix": camera_to_world(view),
            "width": FULL, "height": FULL, "fl_x": 9.5 + view, "fl_y": 9.5 + view, "cx": 4.0, "cy": 4.0 + 0.5 * view,
            "file_paths": [f"{folder}/{name(view, light)}" for light in lights],
            "light_positions": [light_position(light) for light in lights],
            "light_intensities": [[1.0, 0.9 + 0.05 * light, 0.8] for light in lights],
        })
    return frames


def write_images(root: Path, folder: str, size: int, skip: tuple[str, ...] = ()) -> None:
    for view in range(VIEWS):
        for light in range(LIGHTS):
            if f"{name(view, light)}.png" not in skip:
                write_png(root / folder / f"{name(view, light)}.png", image(view, light, size))


def write_json(path: Path, payload: dict) -> None:
    atomic_write_text(path, json.dumps(payload, indent=1) + "\n")


def make_fixtures(out: Path) -> list[Path]:
    """Write every variant under ``out``; returns the variant folders."""
    full, small, splits, nrhints = (out / n for n in ("object_full", "object_small", "split_variants", "nrhints"))
    write_json(full / "transforms_train.json", {"frames": sss3dgs_frames("train")})
    atomic_write_text(full / "exclude_list.txt", "\n".join(EXCLUDED) + "\n")
    write_images(full, "train", FULL, skip=EXCLUDED[:1])
    write_json(small / "transforms_train.json", {"frames": sss3dgs_frames("train")})
    write_images(small, "train", SMALL)
    for suffix, size in (("full", FULL), ("small", SMALL)):
        write_json(splits / f"transforms_train_{suffix}.json", {"frames": sss3dgs_frames(f"train_{suffix}")})
        write_images(splits, f"train_{suffix}", size)
    write_json(nrhints / "transforms_train.json", {"camera_angle_x": 0.9, "frames": [
        {"file_path": f"./train/{name(view, light)}", "transform_matrix": camera_to_world(view),
         "pl_pos": light_position(light), "pl_intensity": [2.0, 2.0, 2.0]}
        for view in range(VIEWS) for light in range(LIGHTS)]})
    write_images(nrhints, "train", FULL)
    return [full, small, splits, nrhints]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parents[1] / "tests" / "fixtures" / "formats")
    for folder in make_fixtures(parser.parse_args().out):
        print(folder)


if __name__ == "__main__":
    main()
