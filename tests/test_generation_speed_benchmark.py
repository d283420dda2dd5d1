"""benchmarks/generation_speed.py: the diffusion stages timed alone and beside a training process."""

from __future__ import annotations

import argparse
import json
import os
import sys

import pytest
import torch
from repo_scripts import load_script
from tiny_models import TINY_NVS, TINY_RELIGHT

from diamond_sss.data.analytic import make_capture_with_test_split
from diamond_sss.diffusion.nvs.model import NVSConfig, NVSModel
from diamond_sss.diffusion.relight.config import RelightModelConfig
from diamond_sss.diffusion.relight.model import RelightDiffusion
from diamond_sss.pipeline.config import PipelineConfig

generation_speed = load_script("benchmarks/generation_speed.py")


def test_each_threads_and_condition_is_timed_and_written(tmp_path):
    data = make_capture_with_test_split(tmp_path / "capture", views=6, lights=3, size=16)
    torch.manual_seed(0)
    config = PipelineConfig(nvs_model=str(NVSModel(NVSConfig(**TINY_NVS)).save(tmp_path / "nvs")),
                            relight_model=str(RelightDiffusion.from_config(RelightModelConfig(**TINY_RELIGHT))
                                              .save(tmp_path / "relight")),
                            nvs_views=2, relight_lights=1, relight_samples=1, min_silhouette_iou=0.0,
                            min_mask_fraction=0.0)
    prelim = tmp_path / "prelim"
    generation_speed.train_from_preset(data, prelim, preset="sss3dgs", regime="views=2,lights=1",
                                       overrides={"iterations": 2, "num_gaussians": 200, "device": "cpu"},
                                       show_progress=False)
    threads = torch.get_num_threads()
    rows = generation_speed.run(data, "views=2,lights=1", prelim, tmp_path / "work", tmp_path / "results", [1],
                                ["alone", "beside"], config)
    assert torch.get_num_threads() == threads  # each row's threads are the benchmark's, not left to the process
    assert [(r["threads"], r["condition"]) for r in rows] == [(1, "alone"), (1, "beside")]
    for r in rows:  # 2 novel views under the real light, then 4 views relit to the missing light
        assert (r["nvs_calls"], r["relit"], r["images"]) == (2, 4, 6)
        assert r["both_s"] == pytest.approx(r["nvs_s"] + r["relight_s"]) and r["nvs_s"] > 0 < r["relight_s"]
    saved = json.loads((tmp_path / "results" / "generation_speed.json").read_text())
    assert saved["rows"] == rows and saved["meta"]["regime"] == "views=2,lights=1"
    table = (tmp_path / "results" / "generation_speed.md").read_text().splitlines()
    assert table[2] == generation_speed.HEADER and len(table) == 4 + len(rows)


def test_the_background_process_runs_inside_the_block_and_not_after(tmp_path):
    marker = tmp_path / "pid"
    command = [sys.executable, "-c",
               f"import os, pathlib, time; pathlib.Path({str(marker)!r}).write_text(str(os.getpid())); time.sleep(60)"]
    with generation_speed.beside(command):
        pid = int(marker.read_text())
        os.kill(pid, 0)  # running
    with pytest.raises(ProcessLookupError):  # stopped and reaped
        os.kill(pid, 0)


def test_negative_threads_are_refused_before_anything_runs(tmp_path):
    with pytest.raises(ValueError, match=r"--threads must be auto or >= 0"):
        generation_speed.run(tmp_path / "none", "all", None, tmp_path / "work", tmp_path / "results", [-1], ["alone"])
    assert not (tmp_path / "work").exists() and not (tmp_path / "results").exists()


def test_threads_are_auto_or_a_count():
    assert generation_speed.threads_value("auto") is None and generation_speed.threads_value("2") == 2
    with pytest.raises(argparse.ArgumentTypeError, match=r"--threads takes auto or a count >= 0.*'-1'"):
        generation_speed.threads_value("-1")
