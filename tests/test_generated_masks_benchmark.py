"""benchmarks/generated_masks.py: a generated mask against the true silhouette (known answers), and the end to end
comparison on a tiny synthetic capture (needs mitsuba)."""

from __future__ import annotations

import importlib.util
import json
import math

import numpy as np
import pytest
from repo_scripts import load_script
from scipy import ndimage

from diamond_sss.data.images import write_png

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


def test_frame_camera_reads_per_frame_intrinsics_or_the_files_angle():
    transforms = {"w": 64, "h": 48, "camera_angle_x": 2.0 * math.atan(0.5)}
    c2w, width, height, focal = masks.frame_camera(transforms, {"transform_matrix": np.eye(4).tolist()})
    assert (width, height) == (64, 48) and focal == pytest.approx(64.0) and c2w.shape == (4, 4)
    frame = {"transform_matrix": np.eye(4).tolist(), "fl_x": 80.0, "cx": 16.0, "cy": 16.0, "w": 32, "h": 32}
    assert masks.frame_camera(transforms, frame)[1:] == (32, 32, 80.0)
    with pytest.raises(ValueError, match="off-centre"):
        masks.frame_camera(transforms, {**frame, "cx": 10.0, "file_paths": ["a.png"]})


def test_a_capture_without_meta_json_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="meta.json"):
        masks.TrueSilhouettes(tmp_path)


@pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="needs mitsuba (renders the true silhouette)")
def test_the_capture_s_own_masks_match_and_grown_ones_are_measured_larger(tmp_path):
    from diamond_sss.synth.render import SynthConfig, synthesize
    from diamond_sss.synth.scene import LightStageConfig

    capture = tmp_path / "capture"
    synthesize(SynthConfig(shape="blob", material="soap", out=capture, size=16, spp=4, seed=0, mesh_resolution=24,
                           stage=LightStageConfig(views=3, lights=1, test_views=0, test_lights=0, fov_x_deg=40.0)))
    truth = masks.TrueSilhouettes(capture)
    real = masks.masks_against_truth(capture / "transforms_train.json", truth)
    assert real["images"] == 3 and real["iou"] > 0.95 and real["area"] == pytest.approx(1.0, abs=0.03)

    # a "pipeline folder" whose generated masks are the capture's, grown by one pixel
    transforms = json.loads((capture / "transforms_train.json").read_text())
    synthetic = tmp_path / "pipeline" / "synthetic"
    synthetic.mkdir(parents=True)
    for index, frame in enumerate(transforms["frames"]):
        coverage = truth.coverage(*masks.frame_camera(transforms, frame))
        grown = ndimage.binary_dilation(coverage >= 0.5)
        write_png(synthetic / f"m{index}.png", (grown * 255).astype(np.uint8))
        frame["file_paths"] = [str((capture / frame["file_paths"][0]).resolve())]
        frame["mask_paths"] = [f"m{index}.png"]
    (synthetic / "transforms_train.json").write_text(json.dumps(transforms))
    generated = masks.masks_against_truth(synthetic / "transforms_train.json", truth)
    assert generated["area"] > 1.1 and generated["fringe"] > real["fringe"] + 0.3
