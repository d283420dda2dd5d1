"""The quality benchmark's bookkeeping (benchmarks/quality.py): variants, run names, where the extra splits are."""

from __future__ import annotations

from pathlib import Path

import pytest
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
