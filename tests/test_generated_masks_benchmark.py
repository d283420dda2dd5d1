"""benchmarks/generated_masks.py: a generated mask against the true silhouette (known answers), and the end to end
comparison on a tiny synthetic capture (needs mitsuba)."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
import torch
from repo_scripts import load_script
from scipy import ndimage

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.images import write_png
from diamond_sss.errors import DataError

masks = load_script("benchmarks/generated_masks.py", "generated_masks_benchmark")


def _disc(radius: float, size: int = 32) -> np.ndarray:
    yy, xx = np.mgrid[:size, :size] + 0.5
    return (np.hypot(xx - size / 2, yy - size / 2) <= radius).astype(np.float64)


def test_a_mask_equal_to_the_truth_scores_its_floor():
    truth = _disc(8.0)
    row = masks.compare(truth, truth)
    assert row["iou"] == 1.0 and row["area"] == 1.0
    assert row["fringe"] == row["truth_fringe"] == 0.0  # a binary truth has no coverage outside its outline
    assert row["rim_deficit"] == 0.0


def test_a_larger_mask_has_area_above_one_and_a_fringe_and_a_smaller_one_a_rim_deficit():
    truth = _disc(8.0)
    grown = ndimage.binary_dilation(truth > 0.5).astype(np.float64)
    shrunk = ndimage.binary_erosion(truth > 0.5).astype(np.float64)
    big, small = masks.compare(grown, truth), masks.compare(shrunk, truth)
    ring = grown.sum() - truth.sum()
    assert big["area"] == pytest.approx(grown.sum() / truth.sum()) and big["area"] > 1.0
    assert big["iou"] == pytest.approx(truth.sum() / grown.sum())
    assert big["fringe"] > 0.0 and big["rim_deficit"] == 0.0
    assert ring > 0 and small["area"] < 1.0 and small["fringe"] == 0.0 and small["rim_deficit"] > 0.0


def test_a_capture_without_meta_json_or_with_a_key_missing_is_refused_naming_it(tmp_path):
    with pytest.raises(FileNotFoundError, match="meta.json"):
        masks.TrueSilhouettes(tmp_path)
    (tmp_path / "meta.json").write_text(json.dumps({"shape": {"name": "sphere", "mesh_resolution": 16},
                                                    "material": {"name": "wax"}}))
    with pytest.raises(DataError, match=r"meta.json: no key 'seed'"):
        masks.TrueSilhouettes(tmp_path)


def test_an_off_centre_camera_is_refused_before_rendering(tmp_path):
    (tmp_path / "meta.json").write_text(json.dumps({"shape": {"name": "sphere", "seed": 0, "mesh_resolution": 16},
                                                    "material": {"name": "wax"}}))
    truth = masks.TrueSilhouettes(tmp_path)
    K = torch.tensor([[40.0, 0.0, 10.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="centred principal point"):
        truth.coverage(torch.eye(4), K, 32, 32)
    assert truth.renderers == {}


@pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="needs mitsuba (renders the true silhouette)")
def test_the_capture_s_own_masks_match_and_grown_ones_are_measured_larger(tmp_path):
    from diamond_sss.synth.render import SynthConfig, synthesize
    from diamond_sss.synth.scene import LightStageConfig

    capture = tmp_path / "capture"
    synthesize(SynthConfig(shape="blob", material="soap", out=capture, size=16, spp=4, seed=0, mesh_resolution=24,
                           stage=LightStageConfig(views=3, lights=1, test_views=0, test_lights=0, fov_x_deg=40.0)))
    truth = masks.TrueSilhouettes(capture)
    real = masks.masks_against_truth(capture, truth)
    assert real["images"] == 3 and real["iou"] > 0.95 and real["area"] == pytest.approx(1.0, abs=0.03)

    # a "pipeline folder" whose generated masks are the capture's, grown by one pixel
    dataset = OLATDataset(capture, "train")
    transforms = json.loads((capture / "transforms_train.json").read_text())
    synthetic = tmp_path / "pipeline" / "synthetic"
    synthetic.mkdir(parents=True)
    for index, frame in enumerate(transforms["frames"]):
        camera = dataset.cameras[dataset.observations[index].view]
        coverage = truth.coverage(camera.w2c, camera.K, camera.width, camera.height)
        grown = ndimage.binary_dilation(coverage >= 0.5)
        write_png(synthetic / f"m{index}.png", (grown * 255).astype(np.uint8))
        frame["file_paths"] = [str((capture / frame["file_paths"][0]).resolve())]
        frame["mask_paths"] = [f"m{index}.png"]
        frame.pop("depth_path", None), frame.pop("normal_path", None)  # a pipeline's generated frames have none
    (synthetic / "transforms_train.json").write_text(json.dumps(transforms))
    generated = masks.masks_against_truth(synthetic, truth)
    assert generated["images"] == 3
    assert generated["area"] > 1.1 and generated["fringe"] > real["fringe"] + 0.3
