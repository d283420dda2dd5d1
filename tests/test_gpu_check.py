"""The GPU check's report machinery (the GPU steps themselves run only on a CUDA machine)."""

from __future__ import annotations

import os
import sys

from repo_scripts import load_script

gpu_check = load_script("scripts/gpu_check.py", "gpu_check")


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
                               "steps_per_second": 200.0}]},
        "demo_training": {"steps": 3000, "seconds": 30.0, "num_gaussians": 9000, "final_loss": 0.01},
        "demo_metrics": {"summary": {"psnr": 30.1}},
    }
    text = gpu_check.markdown(report)
    assert "NVIDIA H100" in text and "| cuda-tests | 0 | 12.0 | 8 passed |" in text
    assert "| cuda | 10000 | 64 | True | 1.00 | 2.00 | 5.00 | 200.0 |" in text
    assert "100.0 steps/s" in text and '"psnr": 30.1' in text
