"""Hyperparameter search: search space, validation split, objective, pruning, failures, a study end to end."""

from __future__ import annotations

import dataclasses
import json
import math
import re

import imageio.v3 as iio
import pytest

pytest.importorskip("optuna", reason="needs Optuna (the 'tune' extra)")
pytest.importorskip("sqlalchemy", reason="needs SQLAlchemy (the 'tune' extra)")

import optuna
import torch
from optuna.trial import TrialState

from diamond_sss.cli.main import main
from diamond_sss.cli.tune_commands import tune
from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture
from diamond_sss.evaluation.evaluate import evaluate_scene
from diamond_sss.training.config import SCHEDULE_KEYS, canonical_key, field_types, scale_schedule
from diamond_sss.training.overrides import make_config
from diamond_sss.training.trainer import ImageSource, Trainer
from diamond_sss.tuning import objective as objective_module
from diamond_sss.tuning.objective import Objective, ObjectiveSettings
from diamond_sss.tuning.report import comparison_table
from diamond_sss.tuning.run import run_study
from diamond_sss.tuning.space import (
    SEARCH_SPACE,
    distributions,
    preset_params,
    suggest_params,
)
from diamond_sss.tuning.study import StudySettings, budget_used, make_storage, open_study, run_worker
from diamond_sss.tuning.validation import holdout_positions, load_tune_data, validation_psnr

# fixed keys that keep a trial tiny: 12 px, few random Gaussians, no multi-view or ray-traced terms
TINY_SETS = ["num_gaussians=64", "init=random", "batch_size=1", "lambda_sil=0", "lambda_depth=0",
             "raytrace_every=1000", "raytrace_gaussians=16", "raytrace_directions=2", "densify=false"]
TINY = {key: value for key, value in (item.split("=") for item in TINY_SETS)}


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("tune_capture")
    make_capture(root, views=4, lights=3, size=12)
    return root


def test_search_space_is_tab4_and_brackets_both_columns():
    tab4 = {"lambda_dssim", "lambda_lpips", "lambda_normal", "lambda_visibility", "lambda_incident_light",
            "lambda_base_color", "lambda_base_color_smooth", "lambda_metallic_smooth", "lambda_roughness_smooth",
            "lambda_subsurfacedness_smooth", "densification_interval", "opacity_reset_interval",
            "densify_from_iter", "densify_until_iter", "densify_grad_threshold"}
    assert set(SEARCH_SPACE) == tab4  # flat names: the trial parameters of every study, old and new
    types = field_types()
    for preset in ("sss3dgs", "diamond"):
        values = preset_params(preset)
        for key, dist in distributions().items():
            value = values[key]
            assert dist.low <= value <= dist.high, (preset, key, value)
            assert isinstance(value, types[canonical_key(key)])
            if isinstance(dist, optuna.distributions.IntDistribution):
                assert (value - dist.low) % dist.step == 0, (preset, key, value)
    fixed = optuna.trial.FixedTrial(preset_params("sss3dgs"))
    assert suggest_params(fixed) == preset_params("sss3dgs")
    with pytest.raises(ValueError, match="not TrainConfig fields: \\['lambda_dsim'\\]"):
        distributions({"lambda_dsim": SEARCH_SPACE["lambda_dssim"]})


def test_schedule_keys_scale_with_the_trial_length():
    params = preset_params("sss3dgs")
    scaled = scale_schedule(params, 0.05, floors={})  # as the trials scale it
    assert (scaled["densification_interval"], scaled["opacity_reset_interval"]) == (5, 150)
    assert (scaled["densify_from_iter"], scaled["densify_until_iter"]) == (25, 750)
    assert all(scaled[k] == params[k] for k in params if canonical_key(k) not in SCHEDULE_KEYS)
    assert all(v == 1 for k, v in scale_schedule(params, 1e-6, floors={}).items()
               if canonical_key(k) in SCHEDULE_KEYS)
    settings = ObjectiveSettings(iterations=500, overrides={"device": "cpu"})
    cfg = settings.trial_config(params)
    assert (settings.scale, cfg.schedule.iterations, cfg.densify.refine_stop_iter,
            cfg.losses.lambda_dssim) == (0.05, 500, 750, 0.2)
    assert cfg.densify.refine_every == 5  # trials keep every searched value distinct: no floors
    with pytest.raises(ValueError, match="schedule scale must be positive"):
        scale_schedule(params, 0.0)


def test_holdout_keeps_every_view_and_light_in_training():
    pairs = [(v, light) for v in range(3) for light in range(3)]
    for seed in range(5):
        held = holdout_positions(pairs, 3, seed)
        assert len(held) == 3 and held == sorted(set(held))
        train = [pairs[i] for i in range(len(pairs)) if i not in held]
        assert {v for v, _ in train} == {0, 1, 2} and {lt for _, lt in train} == {0, 1, 2}
        assert holdout_positions(pairs, 3, seed) == held
    assert len({tuple(holdout_positions(pairs, 3, seed)) for seed in range(5)}) > 1
    assert len(holdout_positions([(0, 0), (1, 1)], 1, 0)) == 1  # no pair keeps both: falls back
    with pytest.raises(ValueError, match="at least one must train"):
        holdout_positions(pairs, 9, 0)
    with pytest.raises(ValueError, match="at least 1 image"):
        holdout_positions(pairs, 0, 0)


def test_validation_split_is_held_out_of_the_training_images(capture):
    data = load_tune_data(capture, validation_images=2, seed=3)
    train = {(o.view, o.light) for o in data.train.observations}
    validation = {(o.view, o.light) for o in data.validation.observations}
    assert len(validation) == 2 and len(train) == 10 and not train & validation
    assert data.train.num_views == data.validation.num_views == 4  # one lattice
    assert data.describe()["validation"] == [list(p) for p in sorted(validation)]
    with pytest.raises(ValueError, match="never looks at the test split"):
        load_tune_data(capture, split="test")


def test_validation_psnr_matches_the_evaluation_and_flags_nan(capture, tmp_path):
    dataset = OLATDataset(capture).subset([0, 5])
    cfg = make_config("diamond", overrides={**TINY, "device": "cpu"})
    scene = Trainer(cfg, [ImageSource(dataset)], tmp_path, show_progress=False).build_scene()
    expected = evaluate_scene(scene, dataset, show_progress=False).summary["psnr"]
    assert validation_psnr(scene, dataset) == pytest.approx(expected, abs=1e-4)
    with torch.no_grad():
        scene.gaussians.params["base_color"].fill_(float("nan"))
    assert math.isnan(validation_psnr(scene, dataset))


def test_comparison_table_known_answer():
    table = comparison_table([("A", {"x": 0.2, "n": 100}), ("B", {"x": 0.00123456, "n": 150})], ["x", "n"],
                             [21.234, None])
    assert table == ("| Hyperparameter | A | B |\n|---|---:|---:|\n| x | 0.2 | 0.00123 |\n| n | 100 | 150 |\n"
                     "| validation PSNR (dB) | 21.23 | - |\n")


def _scripted_study(tmp_path, capture, monkeypatch, psnr_of_trial, fail_training_of=()):
    """A study whose training steps do nothing and whose validation PSNR is scripted per trial."""
    current = {}

    def fake_step(self, scene, optimizers, state, step):
        if current["trial"] in fail_training_of:
            raise FloatingPointError(f"loss is nan at step {step}")
        return {"total": torch.zeros(())}

    def fake_psnr(scene, dataset):
        return psnr_of_trial(current["trial"])

    monkeypatch.setattr(objective_module.Trainer, "training_step", fake_step)
    monkeypatch.setattr(objective_module, "validation_psnr", fake_psnr)
    data = load_tune_data(capture, validation_images=1)
    settings = ObjectiveSettings(overrides={**TINY, "device": "cpu"}, iterations=3, report_every=1)
    objective = Objective(data, settings)

    def tracked(trial):
        current["trial"] = trial.number
        return objective(trial)

    study = open_study(StudySettings(storage=f"sqlite:///{tmp_path / 'study.db'}", pruner_startup_trials=2,
                                     pruner_warmup_steps=2, enqueue_presets=False),
                       settings.fingerprint(data))
    return study, tracked


def test_diverging_trials_fail_and_the_study_goes_on(capture, tmp_path, monkeypatch):
    study, objective = _scripted_study(tmp_path, capture, monkeypatch,
                                       lambda n: math.nan if n == 1 else 20.0, fail_training_of=(0,))
    ran = run_worker(study, objective, 3)
    assert ran == [0, 1, 2]
    states = [t.state for t in study.trials]
    assert states == [TrialState.FAIL, TrialState.FAIL, TrialState.COMPLETE]
    assert "loss is nan" in study.trials[0].user_attrs["failure"]
    assert "validation PSNR is nan" in study.trials[1].user_attrs["failure"]
    assert budget_used(study.trials) == 3


def test_median_pruner_stops_a_poor_trial(capture, tmp_path, monkeypatch):
    study, objective = _scripted_study(tmp_path, capture, monkeypatch, lambda n: 10.0 if n == 2 else 20.0 + n)
    run_worker(study, objective, 3)
    assert [t.state for t in study.trials] == [TrialState.COMPLETE, TrialState.COMPLETE, TrialState.PRUNED]
    assert study.trials[0].intermediate_values == {1: 20.0, 2: 20.0, 3: 20.0}
    assert study.trials[2].intermediate_values == {1: 10.0, 2: 10.0}  # warm-up step 1, pruned at step 2


def test_run_study_is_the_job_behind_the_cli(capture, tmp_path):
    data = load_tune_data(capture, validation_images=1)
    settings = ObjectiveSettings(overrides={**TINY, "device": "cpu"}, iterations=2, report_every=1)
    study = StudySettings(storage=f"sqlite:///{tmp_path / 'study.db'}", pruner_warmup_steps=2)
    with pytest.raises(ValueError, match="--trials 1: a study starts with the two preset trials"):
        run_study(data, tmp_path / "out", settings, study, trials=1)
    result = run_study(data, tmp_path / "out", settings, study, trials=2)
    assert result.ran == [0, 1] and [t.user_attrs["preset"] for t in result.study.trials] == ["sss3dgs", "diamond"]
    assert all(t.intermediate_values.keys() == {1, 2} for t in result.study.trials)
    assert set(result.paths) == {"plot", "table", "config", "best_trial", "trials"} and all(p.is_file() for p in result.paths.values())
    again = run_study(data, tmp_path / "out", settings, study, trials=2, report_only=True)
    assert again.ran == [] and again.study.best_trial.value == result.study.best_trial.value
    typo = dataclasses.replace(study, study_name="diamond-ss")
    with pytest.raises(ValueError, match=re.escape(f"study 'diamond-ss' not found in sqlite:///{tmp_path}/study.db; "
                                                   "studies there: ['diamond-sss']")):
        run_study(data, tmp_path / "out", settings, typo, trials=2, report_only=True)
    assert optuna.get_all_study_names(study.storage) == ["diamond-sss"]  # report-only created nothing


def test_tune_rejects_contradictory_options(capture, tmp_path):
    with pytest.raises(ValueError, match="ask for at least 2 or pass --no-enqueue-presets"):
        tune(capture, tmp_path, trials=1)
    with pytest.raises(ValueError, match="--set lambda_dssim: 'lambda_dssim' is searched"):
        tune(capture, tmp_path, set_=["lambda_dssim=0.3"])
    with pytest.raises(ValueError, match="'iterations' is set by --iterations"):
        tune(capture, tmp_path, set_=["iterations=3"])


def test_bad_storage_urls_give_clear_errors():
    with pytest.raises(ValueError, match="'nonsense' is not an SQLAlchemy URL"):
        make_storage(StudySettings(storage="nonsense"))
    pytest.importorskip("psycopg2", reason="psycopg2 is not installed (the 'tune' extra)")
    masked = "cannot open storage postgresql.*://user:\\*\\*\\*@127.0.0.1:1/db"
    with pytest.raises(ValueError, match=masked) as info:
        make_storage(StudySettings(storage="postgresql://user:secret@127.0.0.1:1/db"))
    assert "secret" not in str(info.value) and "Connection refused" in str(info.value)


def test_tiny_study_end_to_end_on_sqlite(capture, tmp_path):
    out = tmp_path / "tune"
    sets = [*TINY_SETS]
    tune(capture, out, trials=3, iterations=2, report_every=1, validation_images=1, set_=sets, device="cpu")
    study = optuna.load_study(study_name="diamond-sss", storage=f"sqlite:///{out / 'study.db'}")
    trials = study.trials
    assert len(trials) == 3 and all(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in trials)
    assert [t.user_attrs.get("preset") for t in trials[:2]] == ["sss3dgs", "diamond"]
    assert trials[0].params == preset_params("sss3dgs") and trials[1].params == preset_params("diamond")
    assert all(set(t.intermediate_values) <= {1, 2} and t.intermediate_values for t in trials)
    best = study.best_trial
    assert best.value == max(t.value for t in trials if t.state == TrialState.COMPLETE)
    image = iio.imread(out / "parallel_coordinate.png")
    assert image.ndim == 3 and image.shape[1] >= 1000
    table = (out / "tab4.md").read_text()
    assert all(f"| {key} |" in table for key in SEARCH_SPACE) and f"Best (trial {best.number})" in table
    assert f"{best.value:.2f}" in table.splitlines()[-1]
    config = make_config("sss3dgs", config_file=out / "best_config.json")
    assert all(config.get(key) == value for key, value in best.params.items())
    assert (config.gaussians.count, config.gaussians.init, config.losses.lambda_sil) == (64, "random", 0.0)
    assert "iterations" not in json.loads((out / "best_config.json").read_text())
    assert len((out / "trials.csv").read_text().splitlines()) == 4
    main(["train", "--data", str(capture), "--out", str(tmp_path / "run"),
          "--config", str(out / "best_config.json"), "--iterations", "1", "--device", "cpu", "--quiet"])
    assert (tmp_path / "run" / "model.safetensors").is_file()
    with pytest.raises(ValueError, match="created with other settings \\(iterations"):
        tune(capture, out, trials=3, iterations=5, report_every=1, validation_images=1, set_=sets,
             device="cpu")
