"""The quality benchmark's bookkeeping (benchmarks/quality.py): variants, run names, where the extra splits are."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from repo_scripts import load_script

quality = load_script("benchmarks/quality.py", "quality_benchmark")


def test_variants_parse_to_typed_overrides_and_bad_keys_stop_naming_the_variant():
    assert quality.parse_variant("base") == ("base", {})
    name, overrides = quality.parse_variant("ld:sss_light_depth=48,schedule.seed=1,sss_angular_inputs=false")
    assert name == "ld" and overrides == {"sss_light_depth": 48, "schedule.seed": 1, "sss_angular_inputs": False}
    with pytest.raises(SystemExit, match="'typo:sss_widht=3'.*unknown config key"):
        quality.parse_variant("typo:sss_widht=3")


def test_run_folders_are_keyed_by_every_setting_and_by_nothing_else():
    settings = {"sss_light_depth": 48, "iterations": 1000}
    assert quality.settings_hash("diamond", settings) == quality.settings_hash("diamond", dict(reversed(settings.items())))
    assert len({quality.settings_hash("diamond", settings), quality.settings_hash("sss3dgs", settings),
                quality.settings_hash("diamond", {**settings, "iterations": 10000})}) == 3


def _split_files(folder: Path, splits) -> Path:
    folder.mkdir(parents=True)
    for split in splits:
        (folder / f"transforms_{split}.json").write_text("{}")
    return folder


def test_the_cross_splits_are_read_from_the_data_first_then_the_noise_reference(tmp_path):
    data = _split_files(tmp_path / "data", ["train", "test"])
    reference = _split_files(tmp_path / "ref", ["test", "novel_view", "novel_light"])
    assert quality.cross_split_folder(data, reference) == reference
    _split_files(tmp_path / "both", ["novel_view", "novel_light"])
    assert quality.cross_split_folder(tmp_path / "both", reference) == tmp_path / "both"
    with pytest.raises(SystemExit, match="transforms_novel_view.json"):
        quality.cross_split_folder(data, _split_files(tmp_path / "half", ["novel_view"]))


def test_a_given_noise_reference_is_used_as_is_and_nothing_is_rendered_unasked(tmp_path):
    data = _split_files(tmp_path / "data", ["train", "test"])
    given = tmp_path / "given"
    assert quality.noise_reference(data, given, render=True, cross_splits=True, runs=tmp_path) == given
    assert quality.noise_reference(data, None, render=False, cross_splits=False, runs=tmp_path) is None
    rendered = _split_files(tmp_path / "runs" / "noise_reference" / "data", ["test"])
    assert quality.noise_reference(data, None, render=True, cross_splits=False, runs=tmp_path / "runs") == rendered


def _lit_capture(center, lights):
    return SimpleNamespace(bounds=SimpleNamespace(center=torch.tensor(center)), light_positions=torch.tensor(lights))


def test_each_novel_light_is_measured_from_the_scene_centre_to_the_nearest_light_the_run_trained_on():
    center = [1.0, 0.0, 0.0]
    train = _lit_capture(center, [[3.0, 0.0, 0.0], [1.0, 5.0, 0.0], [-1.0, 0.0, 0.0]])
    test = _lit_capture(center, [[2.0, 1.0, 0.0], [1.0, 0.0, 7.0], [0.0, 0.0, 0.0]])
    assert quality.nearest_training_light_deg(train, [0, 1, 2], test) == [45.0, 90.0, 0.0]
    assert quality.nearest_training_light_deg(train, [1], test) == [45.0, 90.0, 90.0]


def test_per_light_psnr_is_the_mean_over_each_lights_images_and_the_table_names_the_angles(tmp_path):
    csv_path = tmp_path / "per_image.csv"
    csv_path.write_text("view,light,psnr,ssim\n0,0,30.0,0.9\n1,0,32.0,0.9\n0,2,28.5,0.8\n")
    values = quality.per_light_psnr(csv_path, 3)
    assert values[0] == 31.0 and values[2] == 28.5 and math.isnan(values[1])
    lines = quality.per_light_table([{"variant": "a", "light_psnr": [31.0, 29.25]}], [[16.24, 30.4]])
    assert lines[0] == "| variant | light 0: PSNR (deg) | light 1: PSNR (deg) |"
    assert lines[2] == "| a | 31.00 (16) | 29.25 (30) |"
