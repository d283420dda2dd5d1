"""Error regions, the noise ceiling, the second render behind it, and the sRGB photometric loss."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from diamond_sss.data.analytic import make_capture
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.data.errors import DataError
from diamond_sss.evaluation.noise import TWO_RENDERS_DB, noise_ceiling
from diamond_sss.evaluation.regions import REGIONS, RegionErrors, error_regions
from diamond_sss.synth.render import image_seed, noise_reference_config, plan_pairs
from diamond_sss.training.overrides import make_config


def _plane_view(size: int = 12):
    """A square patch at depth 2 facing an OpenCV camera at the origin (normals towards the camera: -z)."""
    mask = torch.zeros(size, size, 1)
    mask[2:10, 2:10] = 1.0
    depth = mask * 2.0
    normals = torch.zeros(size, size, 3)
    normals[..., 2] = -1.0
    w2c = torch.eye(4)
    K = torch.tensor([[10.0, 0.0, size / 2], [0.0, 10.0, size / 2], [0.0, 0.0, 1.0]])
    return mask, depth, normals, w2c, K


def test_error_regions_partition_the_frame_by_geometry_and_light():
    mask, depth, normals, w2c, K = _plane_view()
    rgb = mask.expand(-1, -1, 3) * 0.5
    rgb[5, 5] = 0.01  # a dark pixel on the lit face: a cast shadow
    rgb[6, 6] = 0.9  # the brightest: a highlight
    front = error_regions(mask, depth, normals, w2c, K, torch.tensor([0.0, 0.0, 0.0]), rgb)
    cover = torch.stack([front[name] for name in REGIONS]).sum(0)
    assert bool((cover == 1).all()), "regions must be disjoint and cover the frame"
    assert int(front["silhouette"].sum()) == 10 * 10 - 6 * 6  # dilated 10x10 minus eroded 6x6
    assert int(front["background"].sum()) == 12 * 12 - 10 * 10
    assert bool(front["shadow"][5, 5]) and int(front["shadow"].sum()) == 1
    assert bool(front["highlight"][6, 6])
    assert int(front["back_lit"].sum()) == 0
    behind = error_regions(mask, depth, normals, w2c, K, torch.tensor([0.0, 0.0, 3.0]), rgb)
    assert int(behind["back_lit"].sum()) == 36 and int(behind["lit"].sum()) == 0


def test_region_errors_known_answer():
    mask, depth, normals, w2c, K = _plane_view()
    regions = error_regions(mask, depth, normals, w2c, K, torch.zeros(3), mask.expand(-1, -1, 3) * 0.5)
    target = torch.full((12, 12, 3), 0.5)
    pred = target.clone()
    pred[regions["silhouette"]] += 0.1  # MSE 0.01 there: 20 dB
    errors = RegionErrors()
    errors.add(pred, target, regions)
    summary = errors.summary()
    assert summary["silhouette"]["error_share"] == pytest.approx(1.0)
    assert summary["silhouette"]["psnr"] == pytest.approx(20.0, abs=1e-4)
    assert summary["lit"]["psnr"] == 100.0
    assert sum(s["pixel_share"] for s in summary.values()) == pytest.approx(1.0)


def test_noise_ceiling_is_the_psnr_of_two_renders_plus_3db(tmp_path: Path):
    first, second = tmp_path / "a", tmp_path / "b"
    for root in (first, second):
        make_capture(root, views=2, lights=2, size=16, split="test")
    expected = []
    for png in sorted((second / "test").glob("*.png")):
        rgba = iio.imread(png)
        solid = rgba[..., 3] == 255  # premultiplying leaves these pixels' sRGB values as stored
        shifted = rgba.copy()
        shifted[..., :3][solid] = np.minimum(rgba[..., :3][solid].astype(int) + 4, 255).astype(np.uint8)
        iio.imwrite(png, shifted)
        mse = ((shifted[..., :3].astype(float) - rgba[..., :3]) / 255.0) ** 2
        expected.append(10 * math.log10(1.0 / mse.mean()))
    result = noise_ceiling(OLATDataset(first, "test"), OLATDataset(second, "test"))
    assert result["render_psnr"] == pytest.approx(np.mean(expected), abs=1e-3)
    assert result["ceiling_psnr"] == pytest.approx(result["render_psnr"] + 10 * math.log10(2.0))
    assert TWO_RENDERS_DB == pytest.approx(3.0103, abs=1e-4)
    other = tmp_path / "c"
    make_capture(other, views=3, lights=2, size=16, split="test")
    with pytest.raises(ValueError, match="same observations"):
        noise_ceiling(OLATDataset(first, "test"), OLATDataset(other, "test"))


def test_noise_reference_renders_the_same_test_split_with_other_seeds(tmp_path: Path):
    config = noise_reference_config(embedded_dataset(), tmp_path / "ref")
    meta = json.loads((embedded_dataset() / "meta.json").read_text())
    assert (config.shape, config.material, config.spp, config.seed) == ("bunny", "wax", meta["spp"], meta["seed"])
    assert config.stage.test_views == meta["stage"]["test_views"] and not config.train
    pairs = plan_pairs(config)
    assert pairs["train"] == [] and len(pairs["test"]) == 48
    assert image_seed(0, "test", 1, 2) == image_seed(0, "test", 1, 2, noise_seed=0)
    assert image_seed(0, "test", 1, 2, noise_seed=1) != image_seed(0, "test", 1, 2)
    with pytest.raises(DataError, match="meta.json"):
        noise_reference_config(tmp_path, tmp_path / "out")


def test_srgb_photometric_space_weighs_dark_errors_more():
    from diamond_sss.losses.photometric import photometric_loss
    from diamond_sss.training import objective

    assert make_config("diamond").losses.photometric_space == "srgb"  # as the SSS-3DGS release
    with pytest.raises(ValueError, match="photometric_space"):
        make_config("diamond", overrides={"photometric_space": "log"})
    assert make_config("diamond").losses.photometric_error == "l1"  # Eq. A.1
    with pytest.raises(ValueError, match="photometric_error"):
        make_config("diamond", overrides={"photometric_error": "mse"})
    target = torch.full((1, 16, 16, 3), 0.01)
    pred = target + 0.01
    linear = photometric_loss(pred, target, 0.0)
    srgb = photometric_loss(objective.linear_to_srgb(pred), objective.linear_to_srgb(target), 0.0)
    assert float(srgb) > 3 * float(linear)  # the sRGB curve is steep in the dark
