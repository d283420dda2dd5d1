"""The one schedule scaler: train --iterations, the demo's short schedule and the tuning trials."""

from __future__ import annotations

import json

import pytest

from diamond_sss.cli.main import main
from diamond_sss.data.analytic import make_capture
from diamond_sss.training.averaging import averaging_start
from diamond_sss.training.config import FIELDS, scale_schedule, schedule_for, short_schedule
from diamond_sss.training.overrides import (
    config_file_values,
    load_run_config,
    make_config,
    scaled_run_schedule,
    short_run_overrides,
)

DEMO_OVERRIDES_1000 = {  # short_schedule(1000) before the scalers were merged, the short-run model and decay (issue 17;
    # the light map 64 px since session 13, reused for 10 steps since session 14; the MLP's cosines since session 45)
    "iterations": 1000, "position_lr_max_steps": 1000, "batch_size": 1, "num_gaussians": 3000,
    "max_gaussians": 8000, "densify_from_iter": 250, "densify_until_iter": 850, "densification_interval": 125,
    "opacity_reset_interval": 10001, "mv_pairs_per_step": 1, "mv_pixels_per_pair": 256, "raytrace_gaussians": 512,
    "log_every": 50, "checkpoint_every": 500, "sss_lr": 0.005, "sss_width": 64, "lambda_incident_light": 0.0,
    "lr_decay_step": 700, "lr_decay_factor": 0.3, "sss_light_depth": 64, "sss_light_depth_every": 10,
    "sss_lr_warmup_steps": 100, "sss_angular_inputs": True,
}
SPARSE_1000 = {  # a sparse capture's densification threshold and loss weights, the sss3dgs preset's (session 46)
    "densify_grad_threshold": 0.0002, "lambda_dssim": 0.2, "lambda_normal": 0.02, "lambda_base_color": 0.005,
    "lambda_base_color_smooth": 0.006, "lambda_metallic_smooth": 0.002, "lambda_roughness_smooth": 0.002,
    "mv_source_gradient": "centres",  # the multi-view terms move the Gaussian centres only (session 47)
}


def test_demo_overrides_are_unchanged():
    assert short_schedule(1000) == {**DEMO_OVERRIDES_1000, **SPARSE_1000}
    for n in (150, 300, 400, 1000, 1234):
        scaled = short_schedule(n)
        assert (scaled["densify_from_iter"], scaled["densification_interval"]) == (n // 4, n // 8)
        assert (scaled["log_every"], scaled["checkpoint_every"]) == (n // 20, n // 2)
        assert scaled["opacity_reset_interval"] > n  # never reset in a short run
        assert scaled["lr_decay_step"] == 7 * n // 10  # the step decay at 70% of the run
        assert scaled["sss_lr_warmup_steps"] == n // 10  # the MLP's warm-up over the first 10%
    assert short_schedule(1000, dense=True) == {**DEMO_OVERRIDES_1000, "batch_size": 2, "photometric_error": "rmse"}
    assert short_schedule(1000, pipeline_final=True) == {**DEMO_OVERRIDES_1000, "photometric_error": "rmse",
                                                         "lambda_sil": 0.0, "lambda_depth": 0.0, "lambda_mask": 0.5}


def test_the_demo_trains_its_baseline_on_l1_and_its_pipelines_final_reconstruction_on_the_rmse(tmp_path, monkeypatch):
    from diamond_sss.experiments import demo

    class Handed(Exception):
        """Raised by the pipeline's stand-in once both runs' settings were handed over."""

    handed = {}

    def reconstruction(root, run, regime, preset, overrides, *args):
        handed[preset] = overrides
        return {}

    def pipeline(root, out, **kwargs):
        handed["pipeline"] = kwargs["overrides"]
        raise Handed

    monkeypatch.setattr(demo, "_reconstruction", reconstruction)
    monkeypatch.setattr(demo, "run_pipeline", pipeline)
    with pytest.raises(Handed):
        demo.run_demo(tmp_path / "demo", data=tmp_path, iterations=1000, dense=False, show_progress=False)
    baseline = make_config("sss3dgs", overrides=handed["sss3dgs"])
    final = make_config("diamond", overrides=handed["pipeline"])
    assert baseline.losses.photometric_error == "l1" and final.losses.photometric_error == "rmse"
    assert baseline.schedule.iterations == final.schedule.iterations == 1000


def test_only_a_long_dense_run_trains_the_sh_visibility_by_ray_tracing_averages_and_weakens_the_mask_loss():
    for shorter_or_sparse in (short_schedule(2999, dense=True), short_schedule(20000)):  # sparse: not measured
        assert not {"sss_visibility_gradient", "average_last", "lambda_mask"} & set(shorter_or_sparse)
        assert make_config("diamond", overrides=shorter_or_sparse).losses.lambda_mask == 0.1
    for steps, window_start in ((3000, 2700), (10000, 9000)):  # after densification stops at 85% of the run
        long_run = make_config("diamond", overrides=short_schedule(steps, dense=True))
        assert long_run.shading.sss_visibility_gradient is False and long_run.schedule.average_last == 0.1
        assert long_run.losses.lambda_mask == 0.03
        assert averaging_start(steps, long_run.schedule.average_last, long_run.densify.refine_stop_iter) == window_start
    preset = make_config("diamond")  # the presets keep the method's visibility, mask weight and last parameters
    assert preset.shading.sss_visibility_gradient is True and preset.schedule.average_last == 0.0
    assert preset.losses.lambda_mask == 0.1


def test_scale_schedule_rounds_down_keeps_zero_and_other_keys():
    values = {"densify_from_iter": 500, "densification_interval": 150, "position_lr_delay_steps": 0,
              "lambda_dssim": 0.2, "num_gaussians": 5000}
    assert scale_schedule(values, 0.05, floors={}) == {"densify_from_iter": 25, "densification_interval": 7,
                                                       "position_lr_delay_steps": 0, "lambda_dssim": 0.2,
                                                       "num_gaussians": 5000}
    assert scale_schedule(values, 1e-6, floors={})["densification_interval"] == 1
    floored = scale_schedule({**values, "opacity_reset_interval": 3000}, 0.005)
    assert (floored["densification_interval"], floored["opacity_reset_interval"]) == (10, 200)
    assert floored["densify_from_iter"] == 2
    assert scale_schedule({"densification_interval": 4}, 0.5)["densification_interval"] == 4  # below its floor
    assert scale_schedule({"densify_until_iter": 850}, 0.15)["densify_until_iter"] == 127  # 127.5 down
    with pytest.raises(ValueError, match="schedule scale must be positive"):
        scale_schedule(values, 0.0)
    with pytest.raises(ValueError, match="iterations must be positive, got 0"):
        schedule_for({"iterations": 10}, 0)


def test_run_schedule_scales_the_preset_and_config_file_but_not_set_keys(tmp_path):
    scaled, changes = scaled_run_schedule("diamond", 1000)
    assert scaled["schedule.iterations"] == 1000 and scaled["densify.refine_start_iter"] == 50
    assert (scaled["densify.refine_stop_iter"], scaled["densify.refine_every"]) == (1000, 15)
    assert (scaled["runtime.checkpoint_every"], scaled["lr.position_max_steps"]) == (50, 3000)
    assert scaled["densify.reset_every"] == 200  # 100 scaled, kept at the recovery floor
    assert changes["densify.refine_start_iter"] == (500, 50) and "lr.position_delay_steps" not in changes
    best = tmp_path / "best.json"
    best.write_text(json.dumps({"densify_from_iter": 800}))
    scaled, _ = scaled_run_schedule("sss3dgs", 500, given=config_file_values(best), fixed=["checkpoint_every"])
    assert scaled["densify.refine_start_iter"] == 40 and scaled["densify.refine_stop_iter"] == 750
    assert "runtime.checkpoint_every" not in scaled


@pytest.mark.parametrize("keep", [False, True])
def test_train_iterations_scales_the_schedule_unless_kept(tmp_path, capsys, keep):
    make_capture(tmp_path / "data", views=3, lights=2, size=12)
    run = tmp_path / "run"
    tiny = ["--set", "num_gaussians=100", "--set", "lambda_lpips=0", "--set", "raytrace_gaussians=16",
            "--set", "mv_pixels_per_pair=8", "--set", "batch_size=1", "--set", "device=cpu"]
    main(["train", "--data", str(tmp_path / "data"), "--out", str(run), "--iterations", "4", "--quiet",
          "--preset", "diamond", "--set", "log_every=2", *tiny, *(["--keep-schedule"] if keep else [])])
    out = capsys.readouterr().out
    assert json.loads((run / "config.json").read_text())["schedule"]["iterations"] == 4  # written nested
    config = load_run_config(run).flat()
    assert config["iterations"] == 4 and config["log_every"] == 2
    if keep:
        assert "schedule scaled" not in out
        assert (config["densify_from_iter"], config["checkpoint_every"]) == (500, 500)
    else:
        assert "schedule scaled to 4 steps" in " ".join(out.split())
        assert "densify.refine_start_iter 500->1" in " ".join(out.split())
        assert (config["densify_from_iter"], config["densify_until_iter"], config["checkpoint_every"]) == (1, 4, 1)
        assert (run / "checkpoints" / "latest.json").is_file()
        args = ["train", "--data", str(tmp_path / "data"), "--out", str(run), "--iterations", "4", "--quiet",
                "--set", "log_every=2", *tiny, "--resume"]
        main([*args, "--preset", "diamond"])  # a run made with a named preset resumes with it (here: already done)
        assert "trained 4 steps" in capsys.readouterr().out and load_run_config(run).flat() == config
        with pytest.raises(SystemExit):
            main(args)  # the default preset auto resolves to other settings: refused, naming them
        assert "was trained with other settings" in (err := capsys.readouterr().err) and "sss_width: 32 -> 64" in err


def test_config_shows_what_the_default_preset_resolves_to(capsys):
    """``diamond-sss config`` lists the values `train` gives each key: under the default preset auto, the diamond
    preset with the short-run settings for the run's length and capture; a named preset as it is, or scaled."""

    def listed(*args: str) -> dict:
        main(["config", "--json", *args])
        return json.loads(capsys.readouterr().out)

    def values(config) -> dict:
        return {key: config.get(key) for key in FIELDS}

    dense = listed()
    assert dense == values(make_config("diamond", overrides=short_run_overrides(1000, dense=True)))
    assert (dense["schedule.iterations"], dense["schedule.batch_size"], dense["shading.sss_width"]) == (1000, 2, 64)
    assert listed("--preset", "auto", "--regime", "views=3,lights=3", "--iterations", "3000") == values(
        make_config("diamond", overrides=short_run_overrides(3000)))
    assert listed("--preset", "diamond") == listed("--preset", "paper") == values(make_config("diamond"))
    assert listed("--preset", "sss3dgs", "--iterations", "1000") == values(
        make_config("sss3dgs", overrides=scaled_run_schedule("sss3dgs", 1000)[0]))
    main(["config"])
    assert "preset 'auto' = diamond with the short-run settings for 1000 steps, regime all (a dense capture's)" in (
        " ".join(capsys.readouterr().out.split()))
    with pytest.raises(ValueError, match="preset 'auto' is the command line's"):
        make_config("auto")


def test_short_run_overrides_are_the_benchmarks_settings_under_the_config_files(tmp_path):
    """--short-run resolves to the configuration the demo and benchmarks train with (issue 17's dense settings from
    3,000 steps on); a --config file's keys come after it."""
    dense = short_run_overrides(3000, dense=True)
    assert make_config("diamond", overrides=dense) == make_config("diamond", overrides=short_schedule(3000, dense=True))
    assert (dense["schedule.batch_size"], dense["losses.photometric_error"], dense["schedule.average_last"],
            dense["losses.lambda_mask"]) == (2, "rmse", 0.1, 0.03)
    assert (dense["lr.decay_step"], dense["densify.refine_stop_iter"]) == (2100, 2550)
    final = short_run_overrides(1000, pipeline_final=True)
    assert (final["schedule.batch_size"], final["losses.photometric_error"]) == (1, "rmse")
    assert (final["losses.lambda_sil"], final["losses.lambda_depth"], final["losses.lambda_mask"]) == (0.0, 0.0, 0.5)
    sparse = short_run_overrides(1000)  # a sparse train on the real images alone keeps the preset's terms
    assert not {"losses.lambda_sil", "losses.lambda_depth", "losses.lambda_mask"} & set(sparse)
    assert "schedule.average_last" not in final and final["shading.sss_angular_inputs"]
    best = tmp_path / "best.json"
    best.write_text(json.dumps({"sss_lr": 0.002, "lr": {"decay_factor": 0.5}}))
    tuned = short_run_overrides(1000, given=config_file_values(best))
    assert "lr.sss" not in tuned and "lr.decay_factor" not in tuned and tuned["shading.sss_width"] == 64
    resolved = make_config("diamond", overrides=tuned, config_file=best)
    assert (resolved.lr.sss, resolved.lr.decay_factor, resolved.lr.decay_step) == (0.002, 0.5, 700)
    best.write_text("[0.002]")
    with pytest.raises(ValueError, match="best.json: expected a JSON object of config keys"):
        config_file_values(best)
    best.write_text(json.dumps({"sss_lr": "fast"}))
    with pytest.raises(ValueError, match="best.json: .*sss"):
        config_file_values(best)


@pytest.mark.parametrize("flag", [[], ["--short-run"], ["--short-run", "--preset", "auto"]])
@pytest.mark.parametrize(("command", "regime"), [("train", "all"), ("train", "views=3,lights=3"),
                                                 ("run", "views=3,lights=3")])
def test_the_default_preset_trains_with_the_short_run_settings(tmp_path, monkeypatch, capsys, command, regime, flag):
    """No preset flag, --preset auto and the old --short-run give the same run: the diamond preset with the short-run
    settings (a dense capture's on --regime all, the pipeline's final reconstruction's for run)."""
    import dataclasses

    import diamond_sss.pipeline.run as pipeline_run
    import diamond_sss.training.run as training_run

    seen = {}
    monkeypatch.setattr(training_run, "train_run", lambda data, out, config, **kwargs: seen.update(trained=config) or
                        dataclasses.make_dataclass("R", ["steps", "seconds", "num_gaussians", "final_loss"])(1, 0, 1, 0))
    monkeypatch.setattr(pipeline_run, "run_pipeline", lambda data, out, **kwargs: seen.update(kwargs) or {})
    make_capture(tmp_path / "data", views=10, lights=10, size=12)  # 100 images: a dense capture for `train`
    base = [command, "--data", str(tmp_path / "data"), "--out", str(tmp_path / "out"), "--regime", regime, "--quiet"]
    main([*base, *flag, "--iterations", "2000", "--set", "sss_width=32"])
    expected = short_run_overrides(2000, dense=regime == "all", pipeline_final=command == "run")
    said = " ".join(capsys.readouterr().out.split())
    assert "preset auto = diamond with the short-run settings for 2000 steps" in said
    if command == "train":
        assert seen["trained"] == make_config("diamond", overrides={**expected, "sss_width": 32})
        images = 100 if regime == "all" else 9
        assert (f"({'a dense' if regime == 'all' else 'a sparse'} capture's: regime {regime} selects {images} images, "
                "dense from 100)") in said
    else:
        assert seen["preset"] == "diamond"
        assert seen["overrides"] == {**expected, "sss_width": 32}
        assert seen["prelim_overrides"] == {**short_run_overrides(2000), "sss_width": 32}
        assert seen["config"].prelim_preset == "sss3dgs"  # the benchmarks' preliminary reconstruction
        assert "preliminary reconstruction (sss3dgs): the same settings without losses.photometric_error=rmse" in said
        prelim_line = said.split("preliminary reconstruction (sss3dgs):")[1]
        assert "with a sparse capture's" in prelim_line and "losses.lambda_dssim=0.2" in prelim_line  # named, not silent
        main([*base, *flag, "--prelim-preset", "diamond"])
        assert seen["config"].prelim_preset == "diamond"
    main([*base, *flag])
    assert (seen["trained"].schedule.iterations if command == "train" else
            seen["overrides"]["schedule.iterations"]) == 1000
    with pytest.raises(SystemExit):
        main([*base, *flag, "--keep-schedule", "--iterations", "10"])
    assert ("give one of them" if flag else "keeps a named preset's schedule") in capsys.readouterr().err
    for steps in ("0", "-5"):
        with pytest.raises(SystemExit):
            main([*base, *flag, "--iterations", steps])
        assert f"--iterations must be a positive number of training steps, got {steps}" in capsys.readouterr().err


def test_train_takes_a_dense_captures_settings_by_the_images_its_regime_selects(tmp_path, monkeypatch, capsys):
    """A user's sparse capture holds only its images: `--regime all` then selects 9 of them, and the run takes a
    sparse capture's settings (batch 1, L1), not a dense one's; 100 images or more are a dense capture."""
    import dataclasses

    import diamond_sss.training.run as training_run

    seen = {}
    monkeypatch.setattr(training_run, "train_run", lambda data, out, config, **kwargs: seen.update(trained=config) or
                        dataclasses.make_dataclass("R", ["steps", "seconds", "num_gaussians", "final_loss"])(1, 0, 1, 0))
    for views, lights, dense in ((3, 3, False), (10, 9, False), (10, 10, True)):
        data = tmp_path / f"{views}x{lights}"
        make_capture(data, views=views, lights=lights, size=12)
        main(["train", "--data", str(data), "--out", str(tmp_path / "run"), "--quiet"])
        assert seen["trained"] == make_config("diamond", overrides=short_run_overrides(1000, dense=dense))
        assert (seen["trained"].schedule.batch_size, seen["trained"].losses.photometric_error) == (
            (2, "rmse") if dense else (1, "l1"))
        assert f"selects {views * lights} images, dense from 100" in " ".join(capsys.readouterr().out.split())


def test_pipeline_iterations_scale_the_schedule_unless_kept(tmp_path, monkeypatch):
    import diamond_sss.pipeline.run as pipeline_run

    seen = {}
    monkeypatch.setattr(pipeline_run, "run_pipeline", lambda data, out, **kwargs: seen.update(kwargs) or {})
    base = ["run", "--data", str(tmp_path), "--out", str(tmp_path / "out"), "--quiet", "--iterations", "1000",
            "--preset", "diamond"]
    main([*base, "--set", "densification_interval=20"])
    scaled, _ = scaled_run_schedule("diamond", 1000, fixed=["densification_interval"])
    assert seen["overrides"] == {**scaled, "densification_interval": 20}
    assert seen["overrides"]["densify.refine_start_iter"] == 50
    main([*base, "--keep-schedule"])
    assert seen["overrides"] == {"schedule.iterations": 1000}
