"""benchmarks/nvs_speed.py: the novel-view fine-tune's step timed in its parts, per case, with its profile."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from repo_scripts import ROOT, load_script

from diamond_sss.cli.nvs_commands import NVSModelOptions
from diamond_sss.data.embedded import embedded_dataset, finetune_object_names
from diamond_sss.errors import DataError

nvs_speed = load_script("benchmarks/nvs_speed.py")
TINY = NVSModelOptions(image_size=16, block_out_channels=(8, 16, 16), layers_per_block=1)


def test_each_case_is_timed_profiled_and_written(tmp_path):
    data = [embedded_dataset(finetune_object_names()[0])]
    rows = nvs_speed.run(data=data, objects=(1, 2), precisions=("no",), kernels=("deterministic", "autotuned"),
                         timed_steps=1, warmup=1, profile=True, output=tmp_path, model=TINY)
    assert [(r["objects"], r["kernels"]) for r in rows] == [(1, "deterministic"), (1, "autotuned"),
                                                            (2, "deterministic"), (2, "autotuned")]
    for r in rows:
        assert r["images"] == 4 * r["objects"] and r["device"] == "cpu" and r["peak_gib"] is None
        assert r["images_per_second"] == pytest.approx(1e3 * r["images"] / (r["batch_ms"] + r["step_ms"]))
        assert r["operators_per_step"] > 100 and r["cuda_kernels_per_step"] == 0
    saved = json.loads((tmp_path / "nvs_speed.json").read_text())
    assert saved["results"] == rows and saved["meta"]["model"]["image_size"] == 16
    assert (tmp_path / "profile_nvs_cpu_2obj_no_autotuned.txt").read_text().startswith('{"operators_per_step"')
    table = (tmp_path / "nvs_speed.md").read_text().splitlines()
    assert table[2] == nvs_speed.HEADER and len(table) == 4 + len(rows)
    assert all(line.count("|") == table[2].count("|") for line in table[3:])


def test_a_run_without_timed_steps_is_refused(tmp_path):
    with pytest.raises(ValueError, match="--timed-steps must be >= 1"):
        nvs_speed.run(timed_steps=0, output=tmp_path, model=TINY)
    assert not any(tmp_path.iterdir())


def test_a_missing_data_folder_is_named_and_leaves_no_output(tmp_path):
    output = tmp_path / "speed"
    with pytest.raises(DataError, match="missing"):
        nvs_speed.run(data=[tmp_path / "missing"], objects=(1,), precisions=("no",), kernels=("deterministic",),
                      timed_steps=1, warmup=0, output=output, model=TINY)
    assert not output.exists()
    script = subprocess.run([sys.executable, "benchmarks/nvs_speed.py", "--data", str(tmp_path / "missing"),
                             "--output", str(output)], capture_output=True, text=True, cwd=ROOT, check=False)
    assert script.returncode == 1 and "Traceback" not in script.stderr
    assert f"nvs_speed: --data: data folder not found: {tmp_path / 'missing'}" in script.stderr
    assert not output.exists()
