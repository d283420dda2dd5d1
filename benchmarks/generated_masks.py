"""Generated images' masks against the true silhouette at their cameras (issue 58: where the final's halo comes from).

For a pipeline folder (``synthetic/transforms_train.json``, and ``round1/synthetic/`` after two repair rounds) and
the synthetic capture it was cut from (``meta.json``: the procedural shape, rendered again with Mitsuba), every
generated mask ``m`` is compared with the true coverage ``c`` of its camera (box-filtered, as the capture's images):

* ``iou``: ``|m >= 0.5 & c >= 0.5| / |m >= 0.5 | c >= 0.5|``;
* ``area``: ``sum m / sum c`` (1: the generated outline is as large as the object's);
* ``fringe``: mean ``m`` within ``FRINGE_PX`` outside the true outline (``benchmarks/mv_geometry.py``'s fringe, the
  capture's own coverage there is ``truth_fringe``);
* ``rim_deficit``: mean ``1 - m`` within ``RIM_PX`` inside the true outline (an eroded mask).

The capture's training masks are compared the same way (the row ``real``), to show the measure's floor.

    python benchmarks/generated_masks.py outputs/runs/blob_wax/images9_sparse/repair --capture outputs/heldout/blob_wax \
        --real outputs/heldout/blob_wax_sparse9 --out benchmarks/results/generated_masks/blob_wax
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

from diamond_sss.data.images import load_rgba
from diamond_sss.synth.materials import get_material
from diamond_sss.synth.render import OlatRenderer, RenderSettings
from diamond_sss.synth.shapes import build_shape

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mv_geometry import FRINGE_PX, RIM_PX

KEYS = ("iou", "area", "fringe", "truth_fringe", "rim_deficit")


def compare(mask: np.ndarray, coverage: np.ndarray) -> dict[str, float]:
    """The measures of one mask ``[H,W]`` against the true coverage ``[H,W]`` (both in [0, 1])."""
    truth = coverage >= 0.5
    predicted = mask >= 0.5
    outside = ndimage.distance_transform_edt(~truth)
    fringe = (outside > 0) & (outside <= FRINGE_PX)
    rim = truth & (ndimage.distance_transform_edt(truth) <= RIM_PX)
    return {"iou": float((predicted & truth).sum() / max((predicted | truth).sum(), 1)),
            "area": float(mask.sum() / max(coverage.sum(), 1e-9)),
            "fringe": float(mask[fringe].mean()) if fringe.any() else math.nan,
            "truth_fringe": float(coverage[fringe].mean()) if fringe.any() else math.nan,
            "rim_deficit": float((1.0 - mask[rim]).mean()) if rim.any() else math.nan}


class TrueSilhouettes:
    """The capture's object (``meta.json``) rendered for its coverage from any camera of a transforms file."""

    def __init__(self, capture: Path):
        meta_path = capture / "meta.json"
        if not meta_path.is_file():
            raise FileNotFoundError(f"{meta_path}: not a synthetic capture (`diamond-sss synth` writes meta.json)")
        meta = json.loads(meta_path.read_text())
        shape = meta["shape"]
        self.mesh = build_shape(shape["name"], shape["seed"], shape["mesh_resolution"])
        self.material = get_material(meta["material"]["name"])
        self.renderers: dict[tuple[int, int, float], OlatRenderer] = {}

    def coverage(self, c2w: np.ndarray, width: int, height: int, focal_x: float) -> np.ndarray:
        """True coverage ``[H,W]`` of a centred pinhole camera (OpenGL camera-to-world ``c2w``)."""
        key = (width, height, round(focal_x, 4))
        if key not in self.renderers:
            settings = RenderSettings(width=width, height=height, spp=1, fov_x=2.0 * math.atan(0.5 * width / focal_x))
            self.renderers[key] = OlatRenderer(self.mesh, self.material, settings)
        return self.renderers[key].render_geometry(c2w)[0]


def frame_camera(transforms: dict, frame: dict) -> tuple[np.ndarray, int, int, float]:
    """``(c2w, width, height, focal_x)`` of a transforms frame (per-camera intrinsics or the file's angle)."""
    width, height = int(frame.get("w", transforms["w"])), int(frame.get("h", transforms["h"]))
    if "fl_x" in frame:
        if abs(frame.get("cx", 0.5 * width) - 0.5 * width) > 1e-3 or abs(frame.get("cy", 0.5 * height) - 0.5 * height) > 1e-3:
            raise ValueError(f"frame {frame.get('file_paths', ['?'])[0]}: off-centre principal point not supported")
        focal = float(frame["fl_x"])
    else:
        focal = 0.5 * width / math.tan(0.5 * float(transforms["camera_angle_x"]))
    return np.asarray(frame["transform_matrix"], dtype=np.float64), width, height, focal


def masks_against_truth(transforms_path: Path, truth: TrueSilhouettes) -> dict[str, float]:
    """Mean measures over every image of a transforms file (masks from ``mask_paths``, else the images' alpha)."""
    transforms = json.loads(transforms_path.read_text())
    rows = []
    for frame in transforms["frames"]:
        c2w, width, height, focal = frame_camera(transforms, frame)
        coverage = truth.coverage(c2w, width, height, focal)
        masks = frame.get("mask_paths") or [None] * len(frame["file_paths"])
        for image, mask in zip(frame["file_paths"], masks, strict=True):
            _, alpha = load_rgba(transforms_path.parent / image,
                                 transforms_path.parent / mask if mask else None)
            rows.append(compare(np.asarray(alpha, dtype=np.float64).reshape(height, width), coverage))
    if not rows:
        raise ValueError(f"{transforms_path}: no image")
    return {key: float(np.nanmean([row[key] for row in rows])) for key in KEYS} | {"images": len(rows)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("pipelines", type=Path, nargs="+", help="pipeline folders (with synthetic/)")
    parser.add_argument("--capture", type=Path, required=True, help="the full synthetic capture (meta.json)")
    parser.add_argument("--real", type=Path, default=None, help="a data folder whose train split is the real images")
    parser.add_argument("--out", type=Path, default=None, help="write generated_masks.json / .md here")
    args = parser.parse_args()
    truth = TrueSilhouettes(args.capture)
    rows: dict[str, dict[str, float]] = {}
    if args.real is not None:
        rows["real"] = masks_against_truth(args.real / "transforms_train.json", truth)
    for pipeline in args.pipelines:
        stages = [("round 1", pipeline / "round1" / "synthetic"), ("final round", pipeline / "synthetic")]
        found = [(name, folder) for name, folder in stages if (folder / "transforms_train.json").is_file()]
        if not found:
            raise FileNotFoundError(f"{pipeline}: no synthetic/transforms_train.json (not a finished pipeline folder)")
        for name, folder in found:
            rows[f"{pipeline} ({name})"] = masks_against_truth(folder / "transforms_train.json", truth)
    lines = ["| masks | images | " + " | ".join(KEYS) + " |", "|---|---|" + "---|" * len(KEYS)]
    lines += [f"| {name} | {row['images']} | " + " | ".join(f"{row[key]:.3f}" for key in KEYS) + " |"
              for name, row in rows.items()]
    print("\n".join(lines))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "generated_masks.json").write_text(json.dumps(rows, indent=1))
        (args.out / "generated_masks.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
