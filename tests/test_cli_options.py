"""Command-line options derived from the config dataclasses: every field reachable, each default in one place."""

from __future__ import annotations

import dataclasses

import pytest

from diamond_sss.cli.main import main
from diamond_sss.cli.options import config_from, options_of
from diamond_sss.pipeline.config import PipelineConfig


@pytest.fixture
def captured_pipeline(monkeypatch):
    import diamond_sss.pipeline.run as pipeline_run

    seen = {}

    def fake_run_pipeline(data, out, **kwargs):
        seen.update(kwargs)
        return {}

    monkeypatch.setattr(pipeline_run, "run_pipeline", fake_run_pipeline)
    return seen


def test_run_reaches_every_pipeline_field_with_the_configs_defaults(tmp_path, captured_pipeline, capsys):
    base = ["run", "--data", str(tmp_path), "--out", str(tmp_path / "out"), "--quiet"]
    main([*base, "--augment", "none"])
    assert captured_pipeline["config"] == PipelineConfig(augment=())
    main([*base, "--augment", "relight", "--prelim-iterations", "5", "--nvs-guidance", "2.5",
          "--min-silhouette-iou", "0.3", "--min-mask-fraction", "0.01", "--relight-samples", "2", "--device", "cuda",
          "--set", "losses.lambda_dssim=0.3", "--iterations", "7", "--seed", "3"])
    assert captured_pipeline["config"] == PipelineConfig(
        augment=("relight",), prelim_iterations=5, nvs_guidance=2.5, min_silhouette_iou=0.3, min_mask_fraction=0.01,
        relight_samples=2, device="cuda")
    assert captured_pipeline["overrides"] == {"losses.lambda_dssim": 0.3, "iterations": 7}
    assert captured_pipeline["seed"] == 3


def test_options_of_keeps_names_types_defaults_and_help():
    options = options_of(PipelineConfig, exclude=("augment",))
    names = [f.name for f in dataclasses.fields(PipelineConfig)]
    assert [f.name for f in dataclasses.fields(options)] == names[1:]
    assert all(getattr(options(), name) == getattr(PipelineConfig(), name) for name in names[1:])
    assert config_from(PipelineConfig, options(nvs_views=3), augment=("nvs",)) == PipelineConfig(
        augment=("nvs",), nvs_views=3)
