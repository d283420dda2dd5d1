"""The nested config layout and the flat layout of earlier runs and tuning studies: both load, both name keys."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
from gsplat.strategy import DefaultStrategy

from diamond_sss.errors import DataError
from diamond_sss.training.config import FIELDS, FLAT_KEYS, PRESETS, TrainConfig, canonical_key
from diamond_sss.training.overrides import load_run_config, make_config

FLAT_RUN_CONFIG = Path(__file__).parent / "fixtures" / "run_config_flat.json"
"""A run's config.json as written before the groups (one flat object of 72 keys): preset sss3dgs with
FLAT_RUN_SETS."""
FLAT_RUN_SETS = ["lambda_dssim=0.31", "densify_from_iter=250", "mv_pairs_per_step=3", "raytrace_gaussians=77",
                 "sss_lr=0.004", "mixed_precision=false", "percent_dense=0.02", "device=cpu", "num_gaussians=1234",
                 "mv_include_unobserved_views=true"]  # the default until issue 58


def test_a_flat_config_json_of_an_earlier_run_loads_to_the_same_configuration(tmp_path):
    shutil.copy(FLAT_RUN_CONFIG, tmp_path / "config.json")
    loaded = load_run_config(tmp_path)
    assert loaded == make_config("sss3dgs", sets=FLAT_RUN_SETS)
    assert (loaded.losses.lambda_dssim, loaded.densify.refine_start_iter, loaded.multiview.pairs_per_step,
            loaded.raytrace.gaussians, loaded.lr.sss, loaded.shading.mixed_precision, loaded.densify.grow_scale3d,
            loaded.runtime.device, loaded.gaussians.count) == (0.31, 250, 3, 77, 0.004, False, 0.02, "cpu", 1234)
    flat = json.loads(FLAT_RUN_CONFIG.read_text())
    newer = ("prune_opa", "hull_masks", "light_falloff", "sss_angular_inputs",
             "sss_light_depth", "sss_light_depth_every", "sss_lr_warmup_steps",
             "sss_visibility_gradient", "average_last", "sss_position_freqs",
             "photometric_error", "keep_checkpoints", "mv_sil_tolerance", "mv_depth_tolerance",
             "mv_start_fraction", "compile", "mv_source_gradient")  # keys added since: their defaults
    moved = {"synthetic_weight"}  # the pipeline's since issue 61: left out
    assert len(flat) == 72 and {k: v for k, v in loaded.flat().items() if k not in newer} == {
        k: v for k, v in flat.items() if k not in moved}
    (tmp_path / "config.json").write_text(json.dumps(loaded.to_dict()))  # the nested layout written now
    assert load_run_config(tmp_path) == loaded


def test_every_key_has_one_dotted_and_one_flat_name():
    assert len(FIELDS) == len(FLAT_KEYS) == 88
    newer = {"prune_opa", "hull_masks", "light_falloff", "sss_angular_inputs", "sss_light_depth",
             "sss_light_depth_every", "sss_lr_warmup_steps", "sss_visibility_gradient", "average_last",
             "sss_position_freqs", "photometric_error", "keep_checkpoints", "mv_sil_tolerance",
             "mv_depth_tolerance", "mv_start_fraction", "compile", "mv_source_gradient"}
    assert set(json.loads(FLAT_RUN_CONFIG.read_text())) - {"synthetic_weight"} | newer == set(FLAT_KEYS)
    assert all(canonical_key(flat) == dotted and canonical_key(dotted) == dotted for flat, dotted in FLAT_KEYS.items())
    assert canonical_key("densify") == "densify.enabled" and canonical_key("mv_nearest_k") == "multiview.nearest_k"


@pytest.mark.parametrize("form", ["flat", "dotted", "nested"])
def test_sets_overrides_and_config_files_take_dotted_flat_and_nested_keys(tmp_path, form):
    keys = {"flat": ("lambda_dssim", "densification_interval"),
            "dotted": ("losses.lambda_dssim", "densify.refine_every"), "nested": None}[form]
    if keys is None:
        mapping = {"losses": {"lambda_dssim": 0.3}, "densify": {"refine_every": 120}}
    else:
        mapping = {keys[0]: 0.3, keys[1]: 120}
        cfg = make_config("sss3dgs", sets=[f"{keys[0]}=0.3", f"{keys[1]}=120"])
        assert (cfg.losses.lambda_dssim, cfg.densify.refine_every) == (0.3, 120)
    path = tmp_path / "best.json"
    path.write_text(json.dumps(mapping))
    for cfg in (make_config("sss3dgs", overrides=mapping), make_config("sss3dgs", config_file=path)):
        assert (cfg.losses.lambda_dssim, cfg.densify.refine_every, cfg.densify.reset_every) == (0.3, 120, 3_000)
    assert make_config("sss3dgs", config_file=path, sets=["densify.refine_every=7"]).densify.refine_every == 7
    assert make_config("sss3dgs", config_file=path, sets=["densification_interval=8"]).densify.refine_every == 8


def test_unknown_keys_name_similar_keys_in_every_layout(tmp_path):
    with pytest.raises(ValueError, match=r"unknown config key 'lambda_dsim'; similar keys: .*lambda_dssim"):
        make_config(sets=["lambda_dsim=0.3"])
    with pytest.raises(ValueError, match=r"unknown config key 'losses.lambda_dsim'; similar keys: .*lambda_dssim"):
        make_config(overrides={"losses.lambda_dsim": 0.3})
    path = tmp_path / "best.json"
    path.write_text(json.dumps({"losses": {"lambda_dsim": 0.3}}))
    with pytest.raises(ValueError, match=r"best\.json: unknown config key 'losses\.lambda_dsim'"):
        make_config(config_file=path)
    path.write_text(json.dumps({"loss": {"lambda_dssim": 0.3}}))
    with pytest.raises(ValueError, match=r"best\.json: unknown config key 'loss'"):
        make_config(config_file=path)
    (tmp_path / "config.json").write_text(json.dumps({"schedule": {"iterations": "many"}}))
    with pytest.raises(DataError, match=r"config\.json: config key 'schedule\.iterations' expects int"):
        load_run_config(tmp_path)


def test_presets_are_configs_left_unchanged_by_resolution():
    assert all(isinstance(preset, TrainConfig) for preset in PRESETS.values())
    before = json.dumps(PRESETS["sss3dgs"].to_dict())
    cfg = make_config("sss3dgs", sets=["lambda_dssim=0.9", "densify=false"])
    assert (cfg.losses.lambda_dssim, cfg.densify.enabled) == (0.9, False)
    assert json.dumps(PRESETS["sss3dgs"].to_dict()) == before and cfg.losses is not PRESETS["sss3dgs"].losses


def test_densification_is_gsplats_default_strategy():
    kwargs = TrainConfig().densify.strategy_kwargs()
    assert set(kwargs) <= {f.name for f in dataclasses.fields(DefaultStrategy)} and "enabled" not in kwargs
    strategy = DefaultStrategy(**make_config("sss3dgs").densify.strategy_kwargs(), verbose=False)
    assert (strategy.refine_every, strategy.reset_every, strategy.grow_grad2d, strategy.prune_opa) == (
        100, 3_000, 0.0002, 0.005)
