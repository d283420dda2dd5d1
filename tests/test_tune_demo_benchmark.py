"""The tuning demo's bookkeeping (benchmarks/tune_demo.py): arguments, the settings every trial trains with,
the per-trial records and the JSON summary."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("optuna", reason="needs Optuna (the 'tune' extra)")
pytest.importorskip("sqlalchemy", reason="needs SQLAlchemy (the 'tune' extra)")

import optuna
from optuna.trial import TrialState, create_trial
from repo_scripts import ROOT, assert_stops_naming, load_script

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.data.regimes import select_regime
from diamond_sss.training.config import canonical_key
from diamond_sss.training.overrides import make_config, parse_sets
from diamond_sss.tuning.space import SEARCH_SPACE

tune_demo = load_script("benchmarks/tune_demo.py", "tune_demo_benchmark")


def _study() -> optuna.Study:
    """Trials 0 (preset, complete), 1 (pruned after one report), 2 (complete, the best), 3 (failed)."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="maximize")
    study.add_trial(create_trial(state=TrialState.COMPLETE, value=24.5, intermediate_values={20: 22.0, 40: 24.5},
                                 user_attrs={"preset": "sss3dgs", "seconds": 12.5}))
    study.add_trial(create_trial(state=TrialState.PRUNED, intermediate_values={20: 10.0},
                                 user_attrs={"seconds": 3.0}))
    study.add_trial(create_trial(state=TrialState.COMPLETE, value=26.25,
                                 intermediate_values={20: 23.0, 40: 25.0, 60: 26.25}, user_attrs={"seconds": 14.0}))
    study.add_trial(create_trial(state=TrialState.FAIL, user_attrs={"failure": "out of memory"}))
    return study


def test_the_default_regime_fits_the_embedded_demo():
    args = tune_demo.parse_args([])
    selection = select_regime(OLATDataset(embedded_dataset("demo")), args.regime)
    assert (len(selection.views), len(selection.lights)) == (12, 6)


def test_the_summary_goes_to_results_default_the_benchmarks_file_or_the_path_given(tmp_path):
    assert tune_demo.parse_args([]).results == ROOT / "benchmarks" / "results" / "tune_demo.json"
    assert tune_demo.parse_args(["--results", str(tmp_path / "s.json")]).results == tmp_path / "s.json"


def test_the_trial_settings_are_config_keys_the_tune_command_accepts():
    args = tune_demo.parse_args(["--downscale", "4", "--gaussians", "500"])
    sets = parse_sets(tune_demo.trial_sets(args.downscale, args.gaussians))
    refused = {canonical_key(key) for key in SEARCH_SPACE} | {"schedule.iterations"}
    assert refused.isdisjoint(canonical_key(key) for key in sets)
    config = make_config("diamond", overrides=sets)
    assert (config.runtime.downscale, config.gaussians.count) == (4.0, 500)


def test_each_trial_is_recorded_with_its_state_value_preset_seconds_and_reports():
    assert tune_demo.trial_records(_study()) == [
        {"number": 0, "state": "COMPLETE", "value": 24.5, "preset": "sss3dgs", "seconds": 12.5, "reports": 2},
        {"number": 1, "state": "PRUNED", "value": None, "preset": None, "seconds": 3.0, "reports": 1},
        {"number": 2, "state": "COMPLETE", "value": 26.25, "preset": None, "seconds": 14.0, "reports": 3},
        {"number": 3, "state": "FAIL", "value": None, "preset": None, "seconds": None, "reports": 0},
    ]


def test_the_summary_is_json_and_names_the_best_trial_and_the_rounded_wall_time():
    args = tune_demo.parse_args(["--trials", "4"])
    summary = tune_demo.demo_summary(args, Path("demo"), 125.46, _study(), "| key | original | best |\n")
    assert json.loads(json.dumps(summary)) == summary
    assert (summary["best"], summary["seconds_total"], summary["data"]) == (2, 125.5, "demo")
    assert (summary["num_gaussians"], summary["downscale"], summary["regime"]) == (2000, 2.0, "views=12,lights=6")
    assert [t["number"] for t in summary["trials"]] == [0, 1, 2, 3]


@pytest.mark.parametrize("argv, message", [
    (["--trials", "many"], "argument --trials: invalid int value: 'many'"),
    (["--gaussians", "2e3"], "argument --gaussians: invalid int value: '2e3'"),
    (["--downscale", "half"], "argument --downscale: invalid float value: 'half'"),
    (["--report_every", "10"], "unrecognized arguments: --report_every 10"),
])
def test_a_bad_argument_stops_naming_it(argv, message, capsys):
    assert_stops_naming(tune_demo.parse_args, argv, message, capsys)
