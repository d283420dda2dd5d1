"""The sparse-depth benchmark's statistics (benchmarks/sparse_depth.py) on maps with known errors."""

from __future__ import annotations

import math

import pytest
import torch
from repo_scripts import load_script

from diamond_sss.diffusion.nvs.depth_noise import dilate

sparse_depth = load_script("benchmarks/sparse_depth.py", "sparse_depth_benchmark")


def disc(size: int = 32, radius: float = 9.0, depth: float = 4.0) -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(size) - size / 2 + 0.5, torch.arange(size) - size / 2 + 0.5, indexing="ij")
    return (depth * ((x * x + y * y) <= radius * radius).float())[None, None]


def test_the_truth_against_itself_has_no_error():
    truth = disc()
    stats = sparse_depth.depth_stats(truth, truth)
    assert stats["iou"] == 1 and stats["outline_px"] == 0 and stats["far_added"] == 0
    assert stats["median_rel"] == 0 and stats["spread_rel"] == 0


def test_a_scaled_dilated_map_gives_its_scale_and_its_outline_move():
    truth = disc()
    grown = dilate((truth > 0).float(), 1) * 4.4  # 10% farther everywhere, one pixel wider
    stats = sparse_depth.depth_stats(grown, truth)
    assert stats["outline_px"] == 1 and stats["far_added"] == 0
    assert stats["median_rel"] == pytest.approx(0.1) and stats["spread_rel"] == pytest.approx(0.0, abs=1e-6)
    assert stats["iou"] == pytest.approx(float((truth > 0).sum() / (grown > 0).sum()))


def test_a_membrane_counts_as_far_added_support_and_a_gradient_is_smooth():
    truth = disc()
    floater = truth.clone()
    floater[..., 0:4, 0:4] = 4.0  # 16 pixels far outside the disc
    assert sparse_depth.depth_stats(floater, truth)["far_added"] == pytest.approx(16 / float((truth > 0).sum()))
    ramp = truth * (1 + 0.01 * torch.arange(32.0))  # a slow relative error: nearly all low-frequency
    stats = sparse_depth.depth_stats(ramp, truth)
    assert stats["smooth_share"] > 0.9 and stats["spread_rel"] > 0
    noise = truth * (1 + 0.05 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(0)))
    assert sparse_depth.depth_stats(noise, truth)["smooth_share"] < 0.1  # pixel noise: blurred away
    empty = sparse_depth.depth_stats(torch.zeros_like(truth), truth)
    assert empty["iou"] == 0 and math.isnan(empty["median_rel"])


def test_the_figure_panels_share_the_truths_scale_and_colour_the_error_by_sign():
    truth = disc()
    too_far = truth * 1.2
    panels = sparse_depth.depth_panels(truth, too_far, truth)
    assert len(panels) == 4 and all(p.shape == (32, 32, 3) and 0 <= p.min() and p.max() <= 1 for p in panels)
    assert (panels[0] == panels[2]).all() and (panels[0][0, 0] == 0).all()  # same map, same colours; black background
    assert (panels[3][0, 0] == 1).all()  # white where neither map has depth
    red, blue = panels[3][16, 16], sparse_depth.depth_panels(truth, truth * 0.8, truth)[3][16, 16]
    assert red[0] > red[2] and blue[2] > blue[0]  # too far: the warm end; too near: the cool end


def test_a_run_folder_with_a_damaged_record_stops_naming_the_file_and_key(tmp_path):
    (tmp_path / "data.json").write_text("{not json")
    with pytest.raises(SystemExit, match=r"data\.json: no readable 'data'"):
        sparse_depth.recorded(tmp_path / "data.json", "data")
    (tmp_path / "regime.json").write_text('{"spec": "views=3,lights=3"}')
    with pytest.raises(SystemExit, match=r"regime\.json: no readable 'views' \(KeyError"):
        sparse_depth.recorded(tmp_path / "regime.json", "views")
