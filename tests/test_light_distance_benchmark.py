"""The light-distance benchmark's bookkeeping (benchmarks/light_distance.py): views scored, angle bins, table."""

from __future__ import annotations

import math

import pytest
import torch
from repo_scripts import load_script

from diamond_sss.data.regimes import nearest_angle_deg

light_distance = load_script("benchmarks/light_distance.py", "light_distance_benchmark")


def test_the_nearest_angle_is_to_the_closest_reference_direction():
    s = math.sqrt(0.5)
    query = torch.tensor([[1.0, 0.0, 0.0], [s, s, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
    reference = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert torch.allclose(nearest_angle_deg(query, reference), torch.tensor([0.0, 45.0, 90.0, 90.0]), atol=1e-3)


def test_views_are_spread_through_the_runs_views():
    assert light_distance.spread_views([3, 5, 7, 9, 11, 13, 15, 17], 4) == [5, 9, 13, 17]
    assert light_distance.spread_views([3, 5], 8) == [3, 5]
    assert light_distance.spread_views([3, 5, 7], 0) == [3, 5, 7]


def test_lights_are_binned_by_angle_and_the_last_bin_is_open():
    rows = light_distance.bin_rows([0.0, 0.0, 10.0, 14.0, 40.0], [33.0, 35.0, 30.0, 31.0, 20.0], edges=(0.0, 1.0, 12.0))
    assert [(r["from_deg"], r["to_deg"], r["lights"]) for r in rows] == [(0.0, 1.0, 2), (1.0, 12.0, 1),
                                                                        (12.0, math.inf, 2)]
    assert rows[0]["psnr"] == 34.0 and rows[2]["psnr"] == 25.5 and rows[2]["mean_angle_deg"] == 27.0
    text = light_distance.markdown(rows, "title")
    assert text.splitlines()[-1] == "| 12- | 2 | 27.0 | 25.50 |"
    assert text.splitlines()[4] == "| 0-1 | 2 | 0.0 | 34.00 |"


def test_a_regime_that_does_not_fit_the_capture_stops_naming_the_file_and_key(tmp_path):
    path = tmp_path / "regime.json"
    with pytest.raises(SystemExit, match="regime.json: key 'lights': expected a non-empty list"):
        light_distance.check_regime({"views": [0]}, path, 24, tmp_path)
    with pytest.raises(SystemExit, match=r"light 30 is not in --data .* \(lights 0\.\.23\)"):
        light_distance.check_regime({"views": [0], "lights": [1, 30]}, path, 24, tmp_path)
    light_distance.check_regime({"views": [0], "lights": [1, 23]}, path, 24, tmp_path)
