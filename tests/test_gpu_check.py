"""The GPU check's report machinery (the GPU steps themselves run only on a CUDA machine)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest
import torch
import tyro
from repo_scripts import load_script

gpu_check = load_script("scripts/gpu_check.py", "gpu_check")
ROOT = Path(__file__).resolve().parents[1]


def test_a_step_is_logged_with_its_exit_code_and_pytest_summary(tmp_path):
    script = "print('x'); print('== 3 passed, 1 failed in 2.0s =='); raise SystemExit(1)"
    result = gpu_check.run_step("demo", [sys.executable, "-c", script], tmp_path, 60, dict(os.environ))
    assert result["exit_code"] == 1 and (tmp_path / "demo.log").read_text().startswith("x\n")
    assert gpu_check.pytest_counts(result["tail"]) == "3 passed, 1 failed in 2.0s"
    slow = gpu_check.run_step("slow", [sys.executable, "-c", "import time; time.sleep(5)"], tmp_path, 1,
                              dict(os.environ))
    assert slow["exit_code"] == 124 and "timed out" in (tmp_path / "slow.log").read_text()


def test_the_report_lists_machine_steps_speed_and_metrics():
    report = {
        "machine": {"date": "2026-11-23", "gpu": "NVIDIA H100", "gpu_memory_gib": 79.1, "compute_capability": "9.0",
                    "driver": "580", "cuda_runtime": "13.0", "torch": "2.11", "gsplat": "1.5.3", "python": "3.12",
                    "cpu_count": 16},
        "steps": [{"step": "cuda-tests", "exit_code": 0, "seconds": 12.0, "tail": ["8 passed"],
                   "summary": "8 passed"}],
        "speed": {"results": [{"device": "cuda", "gaussians": 10000, "resolution": 64, "multiview": True,
                               "render_forward_ms": 1.0, "render_backward_ms": 2.0, "train_step_ms": 5.0,
                               "steps_per_second": 200.0, "operators_per_step": 3021.4,
                               "cuda_kernels_per_step": 2870.0, "host_syncs_per_step": 4.0}]},
        "nvs_speed": {"results": [{"objects": 8, "precision": "bf16", "kernels": "autotuned", "batch_ms": 2.0,
                                   "step_ms": 38.0, "images_per_second": 800.0, "peak_gib": 3.25,
                                   "host_syncs_per_step": 0.0}]},
        "demo_training": {"steps": 3000, "seconds": 30.0, "num_gaussians": 9000, "final_loss": 0.01},
        "demo_metrics": {"summary": {"psnr": 30.1}},
    }
    text = gpu_check.markdown(report)
    assert "NVIDIA H100" in text and "| cuda-tests | 0 | 12.0 | 8 passed |" in text
    assert "| cuda | 10000 | 64 | True | 1.00 | 2.00 | 5.00 | 200.0 |" in text
    assert "100.0 steps/s" in text and '"psnr": 30.1' in text
    assert "| 10000 | 64 | True | 3021 | 2870 | 4.0 |" in text
    assert "| 8 | bf16 | autotuned | 2.0 | 38.0 | 800 | 3.25 | 0.0 |" in text
    report["nvs_speed"]["results"][0]["peak_gib"] = None  # a CPU row, not profiled
    report["nvs_speed"]["results"][0].pop("host_syncs_per_step")
    assert "| 8 | bf16 | autotuned | 2.0 | 38.0 | 800 | - | - |" in gpu_check.markdown(report)


def test_a_speed_step_is_summarised_by_its_cases_not_its_last_log_line(tmp_path):
    result = {"step": "speed", "exit_code": 0, "tail": ["[W] called a synchronizing CUDA operation"]}
    assert gpu_check.step_summary("speed", result, tmp_path) is None  # no speed.json: the log's last line
    (tmp_path / "speed.json").write_text(json.dumps({"results": [{"device": "cuda"}, {"device": "cuda"}]}))
    assert gpu_check.step_summary("speed", result, tmp_path) == "2 cases (tables below)"
    assert gpu_check.step_summary("speed", {**result, "exit_code": 1}, tmp_path) is None
    assert gpu_check.step_summary("suite", {"tail": ["3 passed, 1 skipped in 2.0s"]}, tmp_path) == "3 passed, 1 skipped in 2.0s"


FAKE_FINETUNE = """
import json, sys
from pathlib import Path
from diamond_sss.diffusion.nvs.model import NVSConfig, NVSModel
args = sys.argv[1:]
run = Path(args[args.index("--out") + 1])
run.mkdir(parents=True, exist_ok=True)
(run / "args.json").write_text(json.dumps(args))
(run / "train_log.jsonl").write_text(json.dumps({"step": 20, "loss": 0.5, "seconds": 0.2}) + "\\n"
                                     + json.dumps({"step": 40, "loss": 0.25, "seconds": 0.125}) + "\\n")
NVSModel(NVSConfig(**json.loads(%r))).save(run / "model")
"""


def test_the_nvs_prior_trains_for_its_minutes_of_wall_time_and_is_exported_in_fp16(tmp_path):
    from tiny_models import TINY_NVS

    from diamond_sss.diffusion.nvs.model import NVSModel

    script = tmp_path / "fake_cli.py"
    script.write_text(FAKE_FINETUNE % json.dumps(TINY_NVS))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT / "src"), os.environ.get("PYTHONPATH")]))}
    result = gpu_check.run_nvs_prior([sys.executable, str(script)], [tmp_path / "capture"], 7.0, tmp_path, env,
                                     init=tmp_path / "earlier_prior")
    assert result["exit_code"] == 0 and result["step"] == "nvs-prior"
    assert result["summary"].startswith("40 steps, loss 0.2500, 0.125 s at the last logged step (float32, from ")
    args = json.loads((tmp_path / "nvs_prior_run" / "args.json").read_text())
    assert args[args.index("--time-limit-s") + 1] == "420"
    assert args[args.index("--mixed-precision") + 1] == "no"  # float32: bf16 was slower
    assert args[args.index("--init-from") + 1] == str(tmp_path / "earlier_prior")
    assert int(args[args.index("--steps") + 1]) == gpu_check.PRIOR_MAX_STEPS
    assert args[args.index("--data") + 1] == str(tmp_path / "capture")
    exported = NVSModel.load(tmp_path / "nvs_prior_model")
    trained = NVSModel.load(tmp_path / "nvs_prior_run" / "model")
    for (key, a), (_, b) in zip(trained.state_dict().items(), exported.state_dict().items()):
        assert torch.equal(b, a.half().float() if a.is_floating_point() else a), key


def test_the_priors_depth_noise_reaches_finetune_nvs(tmp_path, monkeypatch):
    from tiny_models import TINY_NVS

    import diamond_sss.diffusion.nvs.train as nvs_train
    from diamond_sss.cli.main import main

    script = tmp_path / "fake_cli.py"
    script.write_text(FAKE_FINETUNE % json.dumps(TINY_NVS))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT / "src"), os.environ.get("PYTHONPATH")]))}
    result = gpu_check.run_nvs_prior([sys.executable, str(script)], [tmp_path], 1.0, tmp_path, env,
                                     depth_noise=[0.5, 0.15, 1])
    assert result["exit_code"] == 0
    args = json.loads((tmp_path / "nvs_prior_run" / "args.json").read_text())
    seen = {}
    monkeypatch.setattr(nvs_train, "finetune", lambda data, out, config, **_: seen.update(config=config) or out)
    main(args)  # the command the lease runs, parsed by the real command line
    config = seen["config"]
    assert (config.depth_noise_share, config.depth_noise_relative, config.depth_noise_edge_px) == (0.5, 0.15, 1)
    assert config.model.image_size == 64 and config.model.hint_residual


def test_the_prior_options_are_ones_finetune_nvs_takes():
    from diamond_sss.cli.nvs_commands import FinetuneOptions, NVSModelOptions

    fields = set(FinetuneOptions.__dataclass_fields__) | set(NVSModelOptions.__dataclass_fields__)
    options = [a[2:].replace("-", "_") for a in gpu_check.PRIOR_MODEL if a.startswith("--")]
    assert {o.removeprefix("no_") for o in options} <= fields


def test_the_prior_options_parse_in_the_nvs_speed_benchmark(tmp_path):
    nvs_speed = load_script("benchmarks/nvs_speed.py")
    args = [*gpu_check.PRIOR_MODEL, "--profile", "--output", str(tmp_path), "--timed-steps", "0"]
    with pytest.raises(ValueError, match="--timed-steps must be >= 1"):  # parsed; refused before any work
        tyro.cli(nvs_speed.run, args=args)
    summary = gpu_check.step_summary("nvs-speed", {"exit_code": 0, "tail": []}, tmp_path)
    assert summary is None  # no table written
    (tmp_path / "nvs_speed").mkdir()
    rows = [{"objects": 4, "precision": "no", "kernels": "deterministic", "images_per_second": 100.0},
            {"objects": 8, "precision": "bf16", "kernels": "autotuned", "images_per_second": 700.0}]
    (tmp_path / "nvs_speed" / "nvs_speed.json").write_text(json.dumps({"results": rows}))
    assert gpu_check.step_summary("nvs-speed", {"exit_code": 0, "tail": []}, tmp_path) == (
        "2 cases, best 700 images/s (8 objects, bf16, autotuned kernels; table below)")


def test_the_prior_summary_reads_past_a_log_line_cut_short(tmp_path):
    log = tmp_path / "train_log.jsonl"
    assert gpu_check.last_log_record(log) is None
    log.write_text(json.dumps({"step": 20, "loss": 0.5, "seconds": 0.2}) + "\n" + '{"step": 40, "lo')
    assert gpu_check.last_log_record(log) == {"step": 20, "loss": 0.5, "seconds": 0.2}
    log.write_text("not json\n")
    assert gpu_check.last_log_record(log) is None
