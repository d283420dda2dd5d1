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
import torch
from scipy import ndimage

from diamond_sss.data.conventions import opencv_w2c_to_opengl_c2w
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.errors import DataError
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
    """The capture's object (``meta.json``) rendered for its coverage from any pinhole camera."""

    def __init__(self, capture: Path):
        meta_path = capture / "meta.json"
        if not meta_path.is_file():
            raise FileNotFoundError(f"{meta_path}: not a synthetic capture (`diamond-sss synth` writes meta.json)")
        meta = json.loads(meta_path.read_text())
        try:
            shape, material = meta["shape"], meta["material"]["name"]
            self.mesh = build_shape(shape["name"], shape["seed"], shape["mesh_resolution"])
        except KeyError as missing:
            raise DataError(f"{meta_path}: no key {missing} (expected shape.name, shape.seed, "
                            "shape.mesh_resolution and material.name, as `diamond-sss synth` writes)") from None
        self.material = get_material(material)
        self.renderers: dict[tuple[int, int, float], OlatRenderer] = {}

    def coverage(self, w2c: torch.Tensor, K: torch.Tensor, width: int, height: int) -> np.ndarray:
        """True coverage ``[H,W]`` of a camera (OpenCV ``w2c``, pixel ``K`` with a centred principal point)."""
        fx, cx, cy = float(K[0, 0]), float(K[0, 2]), float(K[1, 2])
        if abs(cx - 0.5 * width) > 1e-3 or abs(cy - 0.5 * height) > 1e-3 or abs(float(K[1, 1]) - fx) > 1e-3:
            raise ValueError(f"the true silhouette needs a centred principal point and square pixels, got K={K.tolist()}")
        key = (width, height, round(fx, 4))
        if key not in self.renderers:
            settings = RenderSettings(width=width, height=height, spp=1, fov_x=2.0 * math.atan(0.5 * width / fx))
            self.renderers[key] = OlatRenderer(self.mesh, self.material, settings)
        c2w = opencv_w2c_to_opengl_c2w(w2c.double()).numpy()
        return self.renderers[key].render_geometry(c2w)[0]


def masks_against_truth(data: Path, truth: TrueSilhouettes) -> dict[str, float]:
    """Mean measures over every training image of the data folder ``data`` (each view's truth rendered once)."""
    dataset = OLATDataset(data, "train")
    coverage: dict[int, np.ndarray] = {}
    rows = []
    for index, observation in enumerate(dataset.observations):
        camera = dataset.cameras[observation.view]
        if observation.view not in coverage:
            coverage[observation.view] = truth.coverage(camera.w2c, camera.K, camera.width, camera.height)
        mask = dataset.load(index).mask[..., 0].double().numpy()
        rows.append(compare(mask, coverage[observation.view]))
    if not rows:
        raise DataError(f"{dataset.json_path}: no image")
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
        rows["real"] = masks_against_truth(args.real, truth)
    for pipeline in args.pipelines:
        stages = [("round 1", pipeline / "round1" / "synthetic"), ("final round", pipeline / "synthetic")]
        found = [(name, folder) for name, folder in stages if (folder / "transforms_train.json").is_file()]
        if not found:
            raise FileNotFoundError(f"{pipeline}: no synthetic/transforms_train.json (not a finished pipeline folder)")
        for name, folder in found:
            rows[f"{pipeline} ({name})"] = masks_against_truth(folder, truth)
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
