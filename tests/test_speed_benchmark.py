"""benchmarks/speed.py: a profiled case counts the operators a training step dispatches and writes where it spends."""

from __future__ import annotations

import json

from repo_scripts import load_script

from diamond_sss.data.analytic import make_capture

speed = load_script("benchmarks/speed.py")


def test_a_profiled_case_counts_operators_and_writes_its_tables(tmp_path):
    root = tmp_path / "sphere"
    make_capture(root, views=4, lights=2, size=16)
    plain = speed.time_case(root, 200, 16, "cpu", repeats=1, steps=2, multiview=False, profile_dir=tmp_path)
    both = speed.time_case(root, 200, 16, "cpu", repeats=1, steps=2, multiview=True, profile_dir=tmp_path)
    assert plain["cuda_kernels_per_step"] == 0 and plain["host_syncs_per_step"] == 0  # no CUDA here
    assert 100 < plain["operators_per_step"] < both["operators_per_step"]  # the multi-view losses dispatch more
    text = (tmp_path / "profile_cpu_200x16_plain.txt").read_text()
    assert json.loads(text.splitlines()[0])["operators_per_step"] == plain["operators_per_step"]
    assert "Self CPU" in text and (tmp_path / "profile_cpu_200x16_mv.txt").is_file()
