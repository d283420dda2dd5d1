"""Command-line options derived from the config dataclasses: every field reachable, each default in one place."""

from __future__ import annotations

import dataclasses
import json

import pytest

from diamond_sss.cli.main import main
from diamond_sss.cli.options import config_from, options_of
from diamond_sss.data.analytic import make_capture
from diamond_sss.pipeline.config import PipelineConfig
from diamond_sss.training.overrides import make_config, short_run_overrides


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
    main([*base, "--augment", "none"])  # the default preset auto: the preliminary reconstruction is sss3dgs's
    assert captured_pipeline["config"] == PipelineConfig(augment=(), prelim_preset="sss3dgs")
    main([*base, "--augment", "none", "--preset", "diamond"])
    assert captured_pipeline["config"] == PipelineConfig(augment=())
    main([*base, "--augment", "relight", "--prelim-iterations", "5", "--nvs-guidance", "2.5",
          "--min-silhouette-iou", "0.3", "--min-mask-fraction", "0.01", "--relight-samples", "2", "--device", "cuda",
          "--set", "losses.lambda_dssim=0.3", "--iterations", "7", "--keep-schedule", "--seed", "3",
          "--preset", "diamond"])
    assert captured_pipeline["config"] == PipelineConfig(
        augment=("relight",), prelim_iterations=5, nvs_guidance=2.5, min_silhouette_iou=0.3, min_mask_fraction=0.01,
        relight_samples=2, device="cuda")
    assert captured_pipeline["overrides"] == {"losses.lambda_dssim": 0.3, "schedule.iterations": 7}
    assert captured_pipeline["seed"] == 3
    capsys.readouterr()
    main(base)  # --augment auto: the stages it picked, and why
    said = capsys.readouterr().out
    assert captured_pipeline["config"].augment == ("repair",)  # its model ships with the package
    assert "--augment auto -> repair: render repair (beyond the paper): on four held-out objects" in said
    assert "--rig-framing auto -> prior: the cameras repair generates at are zoomed on the object" in said
    main([*base, "--augment", "nvs,relight"])
    assert "--rig-framing auto -> real: the paper's stages keep the capture's framing" in capsys.readouterr().out
    main([*base, "--augment", "repair", "--rig-framing", "real"])
    assert "--rig-framing" not in capsys.readouterr().out
    main([*base, "--augment", "repair", "--rig", str(tmp_path / "rig.json")])
    assert "--rig-framing auto -> real: a --rig file's cameras keep the intrinsics" in capsys.readouterr().out
    assert "--augment auto" not in (main([*base, "--augment", "none"]) or capsys.readouterr().out)


def test_options_of_keeps_names_types_defaults_and_help():
    options = options_of(PipelineConfig, exclude=("augment",))
    names = [f.name for f in dataclasses.fields(PipelineConfig)]
    assert [f.name for f in dataclasses.fields(options)] == names[1:]
    assert all(getattr(options(), name) == getattr(PipelineConfig(), name) for name in names[1:])
    assert config_from(PipelineConfig, options(nvs_views=3), augment=("nvs",)) == PipelineConfig(
        augment=("nvs",), nvs_views=3)


def test_finetune_nvs_options_are_finetune_config_and_nvs_config_fields(tmp_path, monkeypatch):
    import diamond_sss.diffusion.nvs.train as nvs_train
    from diamond_sss.diffusion.nvs.config import FinetuneConfig, NVSConfig

    seen = {}
    monkeypatch.setattr(nvs_train, "finetune", lambda data, out, config, **_: seen.update(config=config) or out)
    base = ["finetune-nvs", "--out", str(tmp_path / "run"), "--data", str(tmp_path)]
    main(base)
    assert seen["config"] == FinetuneConfig()  # every default from the configs (warp hint on in pixel space)
    main([*base, "--steps", "2000", "--learning-rate", "3e-4", "--prediction-type", "v_prediction",
          "--no-gradient-checkpointing", "--hint-residual", "--log-every", "5"])  # the shipped recipe (README)
    assert seen["config"] == FinetuneConfig(steps=2000, learning_rate=3e-4, gradient_checkpointing=False, log_every=5,
                                            model=NVSConfig(prediction_type="v_prediction", hint_residual=True))
    main([*base, "--image-size", "64", "--block-out-channels", "64", "128", "128", "--layers-per-block", "2"])
    assert seen["config"].model == NVSConfig(image_size=64, block_out_channels=(64, 128, 128), layers_per_block=2)
    main([*base, "--space", "latent", "--vae", str(tmp_path / "vae")])
    assert seen["config"].model == NVSConfig(space="latent", vae_path=str(tmp_path / "vae"), warp_hint=False)


def test_finetune_nvs_from_a_saved_model_takes_its_architecture_unless_told_otherwise(tmp_path, monkeypatch):
    import diamond_sss.diffusion.nvs.train as nvs_train
    from diamond_sss.diffusion.nvs.config import NVSConfig
    from diamond_sss.diffusion.nvs.model import NVSModel

    saved = NVSConfig(image_size=16, block_out_channels=(8, 16, 16), norm_num_groups=4, encoder_channels=(8, 16),
                      cross_attention_dim=16, embed_dim=16, hint_residual=True, prediction_type="v_prediction")
    NVSModel(saved).save(tmp_path / "init")
    seen = {}
    monkeypatch.setattr(nvs_train, "finetune", lambda data, out, config, **_: seen.update(config=config) or out)
    base = ["finetune-nvs", "--out", str(tmp_path / "run"), "--data", str(tmp_path), "--init-from",
            str(tmp_path / "init"), "--mixed-precision", "bf16"]
    main(base)
    assert seen["config"].model == saved and seen["config"].init_from == str(tmp_path / "init")
    assert seen["config"].mixed_precision == "bf16"
    main([*base, "--layers-per-block", "2"])  # an option given wins (and finetune refuses the mismatch)
    assert seen["config"].model.layers_per_block == 2 and seen["config"].model.image_size == 16


def test_finetune_relight_options_are_train_config_and_model_config_fields(tmp_path, monkeypatch):
    import diamond_sss.diffusion.relight.data as relight_data
    import diamond_sss.diffusion.relight.model as relight_model
    import diamond_sss.diffusion.relight.train as relight_train
    from diamond_sss.diffusion.relight.config import (
        RelightAugmentConfig,
        RelightModelConfig,
        RelightTrainConfig,
    )

    seen = {}

    def fake_from_config(config, seed):
        seen.update(model=config, seed=seed)
        return relight_model.RelightDiffusion.__new__(relight_model.RelightDiffusion)

    monkeypatch.setattr(relight_model.RelightDiffusion, "from_config", staticmethod(fake_from_config))
    monkeypatch.setattr(relight_model.RelightDiffusion, "config", RelightModelConfig(), raising=False)
    monkeypatch.setattr(relight_data, "load_finetune_views", lambda resolution: seen.update(resolution=resolution))
    monkeypatch.setattr(relight_train, "finetune", lambda views, out, model, config, **_: seen.update(config=config))
    base = ["finetune-relight", "--out", str(tmp_path / "run"), "--quiet"]
    main(base)
    assert seen["config"] == RelightTrainConfig() and seen["model"] == RelightModelConfig() and seen["seed"] == 0
    main([*base, "--steps", "2000", "--batch-size", "6", "--learning-rate", "1e-3", "--cycle-every", "2",
          "--no-shading-hint", "--resolution", "32", "--seed", "4", "--no-augment"])
    assert seen["config"] == RelightTrainConfig(steps=2000, batch_size=6, learning_rate=1e-3, cycle_every=2, seed=4,
                                                augment=RelightAugmentConfig.off())
    assert seen["model"] == RelightModelConfig(resolution=32, shading_hint=False, residual=False)
    assert seen["seed"] == 4


def test_seed_and_device_flags_left_out_keep_the_config_files_values(tmp_path, monkeypatch):
    """train --seed/--device and ablate --seed override their config keys only when given: a value from
    --config (e.g. tune's best configuration) or --set is not replaced by the flag's default; --set wins over the
    flag, as in make_config."""
    import diamond_sss.training.run as training_run
    from diamond_sss.experiments import ablation

    seen = {}
    monkeypatch.setattr(training_run, "train_run", lambda data, out, config, **kwargs: seen.update(config=config) or
                        dataclasses.make_dataclass("R", ["steps", "seconds", "num_gaussians", "final_loss"])(1, 0, 1, 0))
    make_capture(tmp_path, views=3, lights=2, size=12)
    base = ["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--quiet"]
    main(base)  # the default preset auto: diamond with the short-run settings, no seed or device among them
    assert seen["config"] == make_config("diamond", overrides=short_run_overrides(1000))
    main([*base, "--preset", "diamond"])
    assert seen["config"] == make_config("diamond")
    main([*base, "--preset", "diamond", "--seed", "5", "--device", "cpu"])
    assert seen["config"] == make_config("diamond", overrides={"seed": 5, "device": "cpu"})
    best = tmp_path / "best.json"
    best.write_text(json.dumps({"seed": 7, "device": "cpu", "sss_width": 16}))
    main([*base, "--preset", "diamond", "--config", str(best), "--seed", "5", "--set", "device=auto"])
    assert seen["config"] == make_config("diamond", overrides={"seed": 5, "device": "auto", "sss_width": 16})
    monkeypatch.setattr(ablation, "run_ablation", lambda data, out, **kwargs: seen.update(kwargs) or [])
    main(["ablate", "--data", str(tmp_path), "--out", str(tmp_path / "ablation"), "--set", "seed=3"])
    assert seen["overrides"]["schedule.seed"] == 3
    main(["ablate", "--data", str(tmp_path), "--out", str(tmp_path / "ablation"), "--seed", "4"])
    assert seen["overrides"]["schedule.seed"] == 4
    main(["ablate", "--data", str(tmp_path), "--out", str(tmp_path / "ablation"), "--seed", "4", "--set", "seed=3"])
    assert seen["overrides"]["schedule.seed"] == 3


def test_ablate_trains_the_benchmarks_short_schedule_and_densifies_within_its_steps(tmp_path, monkeypatch):
    """``diamond-sss ablate`` builds each run's config as benchmarks/ablation.py does: the short-run settings
    scaled to --iterations (the preset's 10,000-step schedule would start densifying after the run's end), a dense
    capture's on a regime that selects 100 images or more, --set's last."""
    from diamond_sss.experiments import ablation
    from diamond_sss.training.config import DENSE_SHORT_RUN

    configs = {}

    def fake_train_run(data, run, config, *, regime, **kwargs):
        configs[regime, run.name] = config

    monkeypatch.setattr(ablation, "train_run", fake_train_run)
    monkeypatch.setattr(ablation, "evaluate_run", lambda *args, **kwargs: {"psnr": 0.0, "ssim": 0.0, "mask_iou": 0.0})
    monkeypatch.setattr(ablation, "write_ablation_report", lambda *args: None)
    monkeypatch.setattr(ablation, "save_ablation_figure", lambda *args: None)
    make_capture(tmp_path, views=10, lights=10, size=12)  # 100 images: `all` selects a dense capture
    base = ["ablate", "--data", str(tmp_path), "--out", str(tmp_path / "ablation"), "--quiet"]
    main([*base, "--iterations", "400", "--regimes", "all", "views=3,lights=3"])
    assert len(configs) == 2 * len(ablation.DEFAULT_VARIANTS)
    for (regime, variant), cfg in configs.items():
        densify = cfg.densify
        refine_steps = [step for step in range(cfg.schedule.iterations) if densify.refine_start_iter < step
                        < densify.refine_stop_iter and step % densify.refine_every == 0]
        assert cfg.schedule.iterations == 400 and densify.enabled and len(refine_steps) >= 3, (regime, variant)
        assert densify.reset_every > cfg.schedule.iterations  # the short schedule has no opacity reset
        assert cfg.schedule.batch_size == (DENSE_SHORT_RUN["batch_size"] if regime == "all" else 1)
    assert configs["all", "+both"].losses.lambda_sil == make_config("diamond").losses.lambda_sil
    assert configs["all", "+depth"].losses.lambda_sil == 0.0
    configs.clear()
    main([*base, "--iterations", "400", "--regimes", "all", "--variants", "+both", "--set", "batch_size=3"])
    assert configs["all", "+both"].schedule.batch_size == 3


def test_the_cli_defaults_are_the_experiments_own():
    """The commands spell their defaults out (so that --help does not import torch); they must stay the
    experiments' constants: the demo's 9-image regime and the ablation's dense, 30- and 9-image regimes and
    variants (issue 18: counts, not percentages)."""
    import inspect

    from diamond_sss.cli.demo import demo
    from diamond_sss.cli.train_commands import ablate
    from diamond_sss.experiments.ablation import DEFAULT_VARIANTS, REGIMES
    from diamond_sss.experiments.demo import DEMO_REGIME

    ablate_defaults = inspect.signature(ablate).parameters
    assert ablate_defaults["regimes"].default == list(REGIMES) == ["all", "views=5,lights=6", "views=3,lights=3"]
    assert ablate_defaults["variants"].default == list(DEFAULT_VARIANTS)
    assert inspect.signature(demo).parameters["regime"].default == DEMO_REGIME


def test_diffusion_devices_default_to_auto_and_resolve_to_cuda_when_available(tmp_path, captured_pipeline):
    """`run --device` and `nvs` / `relight --device` default to auto: CUDA when torch sees a GPU, else the CPU; the
    pipeline resolves it once (checked_config), before any stage, and names a bad one."""
    import inspect

    import torch

    from diamond_sss.cli.nvs_commands import nvs
    from diamond_sss.cli.relight_commands import relight
    from diamond_sss.pipeline.run import checked_config

    main(["run", "--data", str(tmp_path), "--out", str(tmp_path / "out"), "--quiet", "--augment", "none"])
    assert captured_pipeline["config"].device == "auto" == PipelineConfig().device
    assert all(inspect.signature(command).parameters["device"].default == "auto" for command in (nvs, relight))
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert checked_config(PipelineConfig()).device == expected
    assert checked_config(PipelineConfig(device="cpu")).device == "cpu"
    assert checked_config(PipelineConfig(device="cuda")).device == "cuda"  # used (or refused) where a stage runs
    with pytest.raises(ValueError, match=r"pipeline config 'device' \(--device\) must be auto \| cpu \| cuda\[:i\], "
                                         r"got 'gpu'"):
        checked_config(PipelineConfig(device="gpu"))
