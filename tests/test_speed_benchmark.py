"""benchmarks/speed.py: a case counts the operators a training step dispatches (its profiled steps over one period of
the ray-traced visibility), writes where it spends, and beside it the plain 3DGS step's row (on CPU: needs CUDA)."""

from __future__ import annotations

import json

from repo_scripts import load_script

from diamond_sss.data.analytic import make_capture

speed = load_script("benchmarks/speed.py")


def test_a_case_counts_operators_writes_its_tables_and_names_the_missing_plain_3dgs_row(tmp_path):
    root = tmp_path / "sphere"
    make_capture(root, views=4, lights=2, size=16)
    plain, none = speed.time_case(root, 200, 16, "cpu", repeats=1, steps=2, multiview=False, profile_dir=tmp_path)
    both, _ = speed.time_case(root, 200, 16, "cpu", repeats=1, steps=2, multiview=True, profile_dir=tmp_path)
    assert none is None  # the plain 3DGS step is gsplat's: asked for on CUDA only
    assert plain["cuda_kernels_per_step"] == 0 and plain["host_syncs_per_step"] == 0  # no CUDA here
    assert plain["peak_gpu_mib"] is plain["step_gpu_mib"] is None and plain["profiled_steps"] == 10  # one ray-tracing period (raytrace.every)
    assert 100 < plain["operators_per_step"] < both["operators_per_step"]  # the multi-view losses dispatch more
    text = (tmp_path / "profile_cpu_200x16_no_mv.txt").read_text()
    assert json.loads(text.splitlines()[0])["operators_per_step"] == plain["operators_per_step"]
    assert "Self CPU" in text and (tmp_path / "profile_cpu_200x16_mv.txt").is_file()
    lines = speed.table_lines([{**plain, "x_plain_3dgs": None}, {**both, "x_plain_3dgs": None}], [])
    assert len(lines) == 5 and {line.count("|") for line in lines} == {15}  # 14 columns in every row
    assert "| cpu | 200 | 16 | plain 3DGS (gsplat) | | | needs CUDA |" in lines[2]
    assert lines[3].startswith("| cpu | 200 | 16 | full objective, multi-view losses off |")
    assert lines[3].endswith(f"| {plain['operators_per_step']:.0f} | n/a | n/a | n/a | n/a |")


def test_the_plain_3dgs_row_is_its_own_ratio_and_the_methods_rows_are_measured_against_it():
    base = {"device": "cuda", "gaussians": 10000, "resolution": 64, "train_step_ms": 2.0, "steps_per_second": 500.0,
            "operators_per_step": 60.0, "cuda_kernels_per_step": 40.0, "host_syncs_per_step": 0.0, "peak_gpu_mib": 50.0,
            "step_gpu_mib": 20.0}
    row = {**base, "multiview": True, "render_forward_ms": 1.0, "render_backward_ms": 2.0, "train_step_ms": 9.0,
           "steps_per_second": 111.1, "operators_per_step": 2000.0, "cuda_kernels_per_step": 1500.0,
           "peak_gpu_mib": 300.0, "step_gpu_mib": 200.0, "x_plain_3dgs": 4.5}
    lines = speed.table_lines([row], [base])
    assert lines[2] == ("| cuda | 10000 | 64 | plain 3DGS (gsplat) | | | 2.00 | 500.0 | 1.00 | 60 | 40 | 0.0 | 50.0 "
                        "| 20.0 |")
    assert lines[3] == ("| cuda | 10000 | 64 | full objective, multi-view losses on | 1.0 | 2.0 | 9.00 | 111.1 | 4.50 "
                        "| 2000 | 1500 | 0.0 | 300.0 | 200.0 |")
