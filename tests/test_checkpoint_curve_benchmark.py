"""The checkpoint-curve benchmark (benchmarks/checkpoint_curve.py): every kept checkpoint scored, files, bad runs."""

from __future__ import annotations

import json
import sys

import pytest
from repo_scripts import load_script

from diamond_sss.data.analytic import make_capture_with_test_split
from diamond_sss.evaluation.run import evaluate_run
from diamond_sss.training.run import train_from_preset

checkpoint_curve = load_script("benchmarks/checkpoint_curve.py", "checkpoint_curve_benchmark")

TINY = {"iterations": 6, "checkpoint_every": 2, "keep_checkpoints": 0, "num_gaussians": 200, "lambda_lpips": 0.0,
        "raytrace_gaussians": 32, "mv_pixels_per_pair": 16, "densify_from_iter": 1, "densification_interval": 2,
        "densify_until_iter": 100, "opacity_reset_interval": 5, "log_every": 1, "image_log_every": 1000,
        "device": "cpu"}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("curve")
    make_capture_with_test_split(root / "capture", views=4, lights=2, size=16)
    train_from_preset(root / "capture", root / "run", overrides=TINY, show_progress=False)
    return root / "run"


def test_every_kept_checkpoint_and_the_saved_model_are_scored_by_step(run, tmp_path, monkeypatch):
    states = checkpoint_curve.scored_states(run)
    assert [step for step, _ in states] == [2, 4, 6]
    assert states[-1][1] == run / "model.safetensors"
    results = tmp_path / "results"
    monkeypatch.setattr(sys, "argv", ["checkpoint_curve.py", "--runs", str(run), "--results", str(results),
                                      "--tag", "t", "--note", "test machine"])
    checkpoint_curve.main()
    curve = json.loads((results / "t.json").read_text())["curves"][checkpoint_curve.run_name(run)]
    assert [row["step"] for row in curve] == [2, 4, 6]
    saved = evaluate_run(run, run.parent / "capture", figures=0, show_progress=False)
    assert curve[-1]["psnr"] == pytest.approx(saved["psnr"], abs=1e-9)  # the last row is the saved model's score
    assert curve[0]["psnr"] != pytest.approx(curve[-1]["psnr"], abs=1e-6)  # the checkpoints hold other states
    table = (results / "t.md").read_text()
    best = max(curve, key=lambda row: row["psnr"])
    assert f"best at step {best['step']} ({best['psnr']:.2f} dB)" in table and "test machine" in table
    assert (results / "t.png").stat().st_size > 0


def test_a_run_without_a_model_or_with_a_damaged_checkpoint_is_named(run, tmp_path, monkeypatch):
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    with pytest.raises(SystemExit, match=f"{unfinished} is not a finished run"):
        checkpoint_curve.scored_states(unfinished)
    damaged = tmp_path / "damaged"
    (damaged / "checkpoints" / "step_00000002").mkdir(parents=True)
    for name in ("model.safetensors", "train_summary.json", "config.json", "data.json"):
        (damaged / name).write_bytes((run / name).read_bytes())
    state = damaged / "checkpoints" / "step_00000002" / "state.json"
    state.write_text("{\"step\": ")
    monkeypatch.setattr(sys, "argv", ["checkpoint_curve.py", "--runs", str(damaged), "--results", str(tmp_path)])
    with pytest.raises(SystemExit, match=f"{state}: damaged or invalid JSON"):
        checkpoint_curve.main()
    monkeypatch.setattr(sys, "argv", ["checkpoint_curve.py", "--runs", str(run), "--data", "a", "b"])
    with pytest.raises(SystemExit, match="--data: 2 captures for 1 runs"):
        checkpoint_curve.main()
