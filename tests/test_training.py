"""Training: config presets and overrides, schedules, checkpoints, resume, the CLI end to end."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import stat

import pytest
import torch

from diamond_sss.cli.main import main
from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture, make_capture_with_test_split
from diamond_sss.evaluation.evaluate import evaluate_scene
from diamond_sss.gaussians.ply import import_ply
from diamond_sss.runs.folder import load_scene
from diamond_sss.scene.io import scene_from_tensors, scene_tensors
from diamond_sss.scene.model import RelightableScene
from diamond_sss.training.averaging import ParameterAverage, averaging_start
from diamond_sss.training.checkpoint import optimizer_from_tensors, optimizer_to_tensors
from diamond_sss.training.config import PRESETS, TrainConfig
from diamond_sss.training.overrides import make_config
from diamond_sss.training.schedules import exponential_lr, linear_warmup, step_decay
from diamond_sss.training.trainer import ImageSource, Trainer
from diamond_sss.utils.io import atomic_save_safetensors, load_safetensors

TINY = {
    "num_gaussians": 300, "batch_size": 2, "lambda_lpips": 0.0, "raytrace_gaussians": 64, "raytrace_every": 2,
    "mv_pixels_per_pair": 32, "mv_pairs_per_step": 1, "densify_from_iter": 1, "densification_interval": 2,
    "densify_until_iter": 100, "opacity_reset_interval": 5, "log_every": 1, "image_log_every": 1000,
    "device": "cpu",
}


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return make_capture_with_test_split(tmp_path_factory.mktemp("capture"), views=6, lights=3, size=16)


def test_presets_follow_the_supplement():
    best = make_config("diamond")
    original = make_config("sss3dgs")
    # Tab. 4, "Best" and "Original"
    assert (best.losses.lambda_dssim, best.losses.lambda_lpips, best.losses.lambda_normal) == (0.492, 0.171, 0.037)
    assert (original.losses.lambda_dssim, original.losses.lambda_lpips,
            original.losses.lambda_normal) == (0.2, 0.2, 0.02)
    assert (best.densify.refine_stop_iter, original.densify.refine_stop_iter) == (10_000, 15_000)
    assert (best.densify.grow_grad2d, original.densify.grow_grad2d) == (0.001, 0.0002)
    assert (best.densify.reset_every, original.densify.reset_every) == (1_000, 3_000)
    assert (best.losses.lambda_sil, best.losses.lambda_depth,
            original.losses.lambda_sil, original.losses.lambda_depth) == (0.5, 0.3, 0, 0)
    # Tab. 3
    assert (best.lr.position_init, best.lr.position_final, best.lr.position_max_steps) == (0.00016, 1.6e-6, 30_000)
    assert (best.lr.opacity, best.lr.scaling, best.shading.sss_width,
            best.shading.light_init) == (0.05, 0.005, 32, -1.0)
    assert PRESETS["diamond"] == TrainConfig() and best == PRESETS["diamond"]
    with pytest.raises(dataclasses.FrozenInstanceError):  # a resolved config is frozen: passed down, not edited
        best.losses.lambda_dssim = 0.9
    assert make_config("diamond").losses.lambda_dssim == PRESETS["diamond"].losses.lambda_dssim == 0.492


def test_overrides_sets_and_config_files(tmp_path):
    cfg = make_config("sss3dgs", sets=["lambda_dssim=0.3", "densify=false", "iterations=1e3"])
    assert (cfg.losses.lambda_dssim, cfg.densify.enabled, cfg.schedule.iterations) == (0.3, False, 1000)
    path = tmp_path / "best.json"
    path.write_text(json.dumps({"lambda_normal": 0.05, "densification_interval": 120}))
    cfg = make_config("diamond", config_file=path, sets=["lambda_normal=0.06"])
    assert (cfg.losses.lambda_normal, cfg.densify.refine_every) == (0.06, 120)
    with pytest.raises(ValueError, match="unknown config key 'lambda_dsim'"):
        make_config(sets=["lambda_dsim=0.3"])
    with pytest.raises(ValueError, match="'iterations' expects int, got '1.5'"):
        make_config(sets=["iterations=1.5"])
    with pytest.raises(ValueError, match="--set expects key=value"):
        make_config(sets=["lambda_dssim"])
    with pytest.raises(ValueError, match="config key 'losses.lambda_mask' must be >= 0"):
        make_config(sets=["lambda_mask=-1"])
    with pytest.raises(ValueError, match="config key 'lr.decay_factor' must be >= 0, got -1.0"):
        make_config(sets=["lr.decay_factor=-1"])  # a negative rate would climb the loss without a word
    with pytest.raises(ValueError, match="config key 'lr.sss' must be >= 0"):
        make_config(sets=["sss_lr=-0.001"])
    assert make_config(sets=["lr.decay_factor=0"]).lr.decay_factor == 0.0  # 0 freezes: allowed
    path.write_text(json.dumps({"lambda_normal": "high"}))
    with pytest.raises(ValueError, match=r"best.json: config key 'lambda_normal' expects float"):
        make_config(config_file=path)
    with pytest.raises(ValueError, match="unknown preset"):
        make_config("fast")



@pytest.mark.parametrize(("given", "message"), [
    ("lambda_depth=-0.1", "config key 'losses.lambda_depth' must be >= 0, got -0.1"),
    ("iterations=0", "config key 'schedule.iterations' must be positive, got 0"),
    ("lambda_dssim=1.5", r"config key 'losses.lambda_dssim' must be in \[0, 1\], got 1.5"),
    ("mv_start_fraction=1", r"config key 'multiview.start_fraction' must be in \[0, 1\), got 1.0"),
    ("mv_sil_tolerance=0", r"config key 'multiview.sil_tolerance' must be in \(0, 1\], got 0.0"),
    ("mv_depth_tolerance=-0.01", "config key 'multiview.depth_tolerance' must be >= 0, got -0.01"),
    ("prune_opa=2", r"config key 'densify.prune_opa' must be in \[0, 1\], got 2.0"),
    ("raytrace_directions=-1", "config key 'raytrace.directions' must be >= 0, got -1"),
])
def test_a_value_out_of_range_is_refused_when_the_config_is_made_before_a_run_writes_anything(
        capture, tmp_path, capsys, given, message):
    """Ranges are checked by make_config, naming the key, what it expects and what was given: `train` stops before
    its run folder (config.json, regime.json) exists, not at the first training step."""
    with pytest.raises(ValueError, match=message):
        make_config(sets=[given])
    run = tmp_path / "run"
    with pytest.raises(SystemExit):
        main(["train", "--data", str(capture), "--out", str(run), "--quiet", "--set", given])
    assert message.replace("\\", "").split(" must")[0] in capsys.readouterr().err
    assert not run.exists()

def test_exponential_lr_schedule():
    assert exponential_lr(0, 1e-2, 1e-4, 100) == pytest.approx(1e-2)
    assert exponential_lr(100, 1e-2, 1e-4, 100) == pytest.approx(1e-4)
    assert exponential_lr(500, 1e-2, 1e-4, 100) == pytest.approx(1e-4)
    assert exponential_lr(50, 1e-2, 1e-4, 100) == pytest.approx(1e-3)  # geometric mean halfway
    assert exponential_lr(0, 1e-2, 1e-4, 100, delay_steps=10, delay_mult=0.01) == pytest.approx(1e-4)
    assert exponential_lr(10, 1e-2, 1e-4, 100, delay_steps=10, delay_mult=0.01) == pytest.approx(
        math.exp(0.9 * math.log(1e-2) + 0.1 * math.log(1e-4)))
    assert (step_decay(49_999, 50_000, 0.1), step_decay(50_000, 50_000, 0.1)) == (1.0, 0.1)
    assert [linear_warmup(step, 4) for step in range(6)] == [0.25, 0.5, 0.75, 1.0, 1.0, 1.0]
    assert linear_warmup(0, 0) == 1.0


def test_optimizer_state_round_trip(tmp_path):
    param = torch.nn.Parameter(torch.randn(5, 3))
    optimizer = torch.optim.Adam([param], lr=0.1)
    param.grad = torch.randn(5, 3)
    optimizer.step()
    tensors, meta = optimizer_to_tensors("means", optimizer)
    atomic_save_safetensors(tmp_path / "optimizer.safetensors", tensors)  # through the file, as a checkpoint
    restored = torch.nn.Parameter(param.detach().clone())
    restored_opt = torch.optim.Adam([restored], lr=0.5)
    restored_opt.load_state_dict(optimizer_from_tensors("means", load_safetensors(tmp_path / "optimizer.safetensors"),
                                                        json.loads(json.dumps(meta))))
    assert restored_opt.param_groups[0]["lr"] == 0.1
    for key in ("step", "exp_avg", "exp_avg_sq"):
        assert torch.equal(restored_opt.state[restored][key], optimizer.state[param][key]), key
    # exact resume: the next step of the restored optimizer is the original's, to the bit (Adam's bias
    # correction reads the step count, its update both moments)
    param.grad = restored.grad = torch.randn(5, 3)
    optimizer.step()
    restored_opt.step()
    assert torch.equal(restored, param)


class _Killed(RuntimeError):
    pass


class _KilledTrainer(Trainer):
    """Dies at step ``kill_at`` (after the checkpoint of the previous step was written)."""

    kill_at = 4

    def training_step(self, scene, optimizers, strategy_state, step):
        if step == self.kill_at:
            raise _Killed()
        return super().training_step(scene, optimizers, strategy_state, step)


def test_resume_after_a_kill_matches_an_uninterrupted_run(capture, tmp_path):
    cfg = make_config("diamond", overrides={**TINY, "iterations": 6, "checkpoint_every": 2})
    dataset = OLATDataset(capture)
    straight = Trainer(cfg, [ImageSource(dataset)], tmp_path / "a", show_progress=False)
    straight.run()
    with pytest.raises(_Killed):
        _KilledTrainer(cfg, [ImageSource(dataset)], tmp_path / "b", show_progress=False).run()
    assert (tmp_path / "b" / "checkpoints" / "latest.json").is_file()
    resumed = Trainer(cfg, [ImageSource(dataset)], tmp_path / "b", show_progress=False)
    resumed.run(resume=True)
    a = load_safetensors(tmp_path / "a" / "model.safetensors")
    b = load_safetensors(tmp_path / "b" / "model.safetensors")
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    history = json.loads((tmp_path / "b" / "train_summary.json").read_text())["history"]
    assert [h["step"] for h in history] == [1, 2, 3, 4, 5, 6]


def test_every_checkpoint_is_kept_on_request_and_holds_its_steps_scene(capture, tmp_path):
    cfg = make_config("diamond", overrides={**TINY, "iterations": 6, "checkpoint_every": 2, "keep_checkpoints": 0})
    Trainer(cfg, [ImageSource(OLATDataset(capture))], tmp_path, show_progress=False).run()
    folders = sorted(p.name for p in (tmp_path / "checkpoints").iterdir() if p.is_dir())
    assert folders == ["step_00000002", "step_00000004"]  # the last step writes the model, not a checkpoint
    shorter = make_config("diamond", overrides={**TINY, "iterations": 4})
    Trainer(shorter, [ImageSource(OLATDataset(capture))], tmp_path / "four", show_progress=False).run()
    step4 = load_safetensors(tmp_path / "checkpoints" / "step_00000004" / "scene.safetensors")
    model = load_safetensors(tmp_path / "four" / "model.safetensors")  # the same steps, stopped at 4
    assert step4.keys() == model.keys() and all(torch.equal(step4[key], model[key]) for key in model)
    with pytest.raises(ValueError, match="config key 'runtime.keep_checkpoints' must be >= 0, got -1"):
        make_config(sets=["keep_checkpoints=-1"])


def test_reused_light_maps_resume_exactly_and_render_each_light_once_per_window(capture, tmp_path, monkeypatch):
    size = 12  # no other pass renders at this size
    light_map_renders = []
    render_geometry = RelightableScene.render_geometry

    def counting(self, viewmats, Ks, width, height, backend="auto"):
        if width == size:
            light_map_renders.append(viewmats.shape[0])
        return render_geometry(self, viewmats, Ks, width, height, backend)

    monkeypatch.setattr(RelightableScene, "render_geometry", counting)
    settings = {**TINY, "iterations": 7, "checkpoint_every": 3, "sss_light_depth": size, "sss_light_depth_every": 4}
    cfg = make_config("diamond", overrides=settings)
    dataset = OLATDataset(capture)
    straight = Trainer(cfg, [ImageSource(dataset)], tmp_path / "a", show_progress=False)
    straight.run()
    # 3 lights, 2 images a step; windows of 4 steps, also ended by the checkpoints after steps 3 and 6: at most one
    # map per light in each of the windows of steps [0, 3), [3, 4), [4, 6), [6, 7), instead of 14; plus the one
    # image logged at the end, rendered without the cache
    assert sum(light_map_renders) <= 3 + 2 + 3 + 2 + 1
    with pytest.raises(_Killed):
        _KilledTrainer(cfg, [ImageSource(dataset)], tmp_path / "b", show_progress=False).run()
    Trainer(cfg, [ImageSource(dataset)], tmp_path / "b", show_progress=False).run(resume=True)
    a = load_safetensors(tmp_path / "a" / "model.safetensors")
    b = load_safetensors(tmp_path / "b" / "model.safetensors")
    for key in a:
        assert torch.equal(a[key], b[key]), key
    every_step = make_config("diamond", overrides={**settings, "sss_light_depth_every": 1})
    Trainer(every_step, [ImageSource(dataset)], tmp_path / "c", show_progress=False).run()
    c = load_safetensors(tmp_path / "c" / "model.safetensors")
    assert not torch.equal(a["gaussians.params.means"], c["gaussians.params.means"])  # the reuse changes the run


def test_parameter_average_is_the_running_mean_and_keeps_the_last_integer_tensors():
    steps = [{"w": torch.tensor([1.0, 2.0]) * k, "n": torch.tensor([k])} for k in (1, 2, 3, 4)]
    average = ParameterAverage()
    for tensors in steps:
        average.add(tensors)
    assert average.count == 4 and steps[0]["w"].tolist() == [1.0, 2.0]  # the inputs are not changed
    assert torch.allclose(average.mean["w"], torch.tensor([2.5, 5.0])) and average.mean["n"].tolist() == [4]
    with pytest.raises(ValueError, match="'w' changed shape"):
        average.add({"w": torch.zeros(3), "n": torch.tensor([5])})
    assert average.count == 4
    # the window: the last 10% of 100 steps, but not before densification stops; none for 0
    assert (averaging_start(100, 0.1, 50), averaging_start(100, 0.1, 95), averaging_start(100, 0.0, 0)) == (90, 95, 100)
    with pytest.raises(ValueError, match=r"'schedule.average_last' must be in \[0, 1\), got 1.0"):
        make_config(sets=["average_last=1"])


def test_averaged_model_is_the_mean_of_the_last_steps_and_resumes_exactly(capture, tmp_path):
    settings = {**TINY, "iterations": 6, "checkpoint_every": 2, "densify_until_iter": 3, "average_last": 0.5}
    cfg = make_config("diamond", overrides=settings)
    dataset = OLATDataset(capture)
    seen: list[dict] = []

    def keep(done, scene, terms):
        seen.append({k: v.clone() for k, v in scene_tensors(scene).items()})

    result = Trainer(cfg, [ImageSource(dataset)], tmp_path / "a", show_progress=False).run(on_step=keep)
    a = load_safetensors(tmp_path / "a" / "model.safetensors")
    assert result.averaged_steps == 3  # steps 4-6
    assert json.loads((tmp_path / "a" / "train_summary.json").read_text())["averaged_steps"] == 3
    for key, value in a.items():
        if value.is_floating_point():
            torch.testing.assert_close(value, torch.stack([s[key] for s in seen[3:]]).mean(0), rtol=1e-5, atol=1e-6)
    assert not torch.equal(a["gaussians.params.means"], seen[-1]["gaussians.params.means"])
    # killed after the checkpoint of step 4, whose mean holds one step, and resumed: the same model, bit for bit
    with pytest.raises(_Killed):
        _KilledTrainer(cfg, [ImageSource(dataset)], tmp_path / "b", show_progress=False).run()
    Trainer(cfg, [ImageSource(dataset)], tmp_path / "b", show_progress=False).run(resume=True)
    b = load_safetensors(tmp_path / "b" / "model.safetensors")
    for key in a:
        assert torch.equal(a[key], b[key]), key
    # a step-4 checkpoint whose state lost the mean's step count is damaged: the resume falls back to step 2's
    with pytest.raises(_Killed):
        _KilledTrainer(cfg, [ImageSource(dataset)], tmp_path / "c", show_progress=False).run()
    state = tmp_path / "c" / "checkpoints" / "step_00000004" / "state.json"
    meta = json.loads(state.read_text())
    del meta["extra"]["averaged_steps"]
    state.write_text(json.dumps(meta))
    Trainer(cfg, [ImageSource(dataset)], tmp_path / "c", show_progress=False).run(resume=True)
    c = load_safetensors(tmp_path / "c" / "model.safetensors")
    for key in a:
        assert torch.equal(a[key], c[key]), key
    # a window that would begin while the Gaussians are densified begins when densification stops
    longer = make_config("diamond", overrides={**settings, "average_last": 0.9})
    assert Trainer(longer, [ImageSource(dataset)], None, show_progress=False).run().averaged_steps == 3


def test_the_position_encoding_key_sizes_the_mlp_and_the_scene_reloads_with_it(capture):
    cfg = make_config("diamond", overrides={**TINY, "sss_position_freqs": 0})
    scene = Trainer(cfg, [ImageSource(OLATDataset(capture))], None, show_progress=False).build_scene()
    assert scene.mlp.config.num_freqs == 0
    assert scene.mlp.input_dim == RelightableScene(scene.gaussians).mlp.input_dim - 3 * 2 * 4  # 4 frequencies: 24 more
    tensors = scene_tensors(scene)
    assert scene_from_tensors(tensors, cfg.shading).mlp.config.num_freqs == 0
    with pytest.raises(RuntimeError, match="size mismatch"):
        scene_from_tensors(tensors, make_config("diamond", overrides=TINY).shading)


def test_training_improves_the_fit(capture, tmp_path):
    cfg = make_config("diamond", overrides={**TINY, "iterations": 30, "densify": False})
    dataset = OLATDataset(capture)
    trainer = Trainer(cfg, [ImageSource(dataset)], tmp_path / "run", show_progress=False)
    before = evaluate_scene(trainer.build_scene(), dataset, show_progress=False).summary
    result = trainer.run()
    after = evaluate_scene(trainer.scene, dataset, show_progress=False).summary
    assert after["psnr"] > before["psnr"] + 0.5
    assert trainer.init_source == "visual_hull"
    assert result.num_gaussians == 300  # densify=False keeps the count fixed
    assert {"mv_silhouette", "mv_depth", "raytrace", "mask", "normal"} <= set(result.history[0])


def test_step_callback_sees_every_step_and_can_stop_the_run(capture, tmp_path):
    cfg = make_config("sss3dgs", overrides={**TINY, "iterations": 6, "densify": False, "log_every": 4})
    dataset = OLATDataset(capture)
    seen = []

    def stop_at_three(done, scene, terms):
        seen.append((done, scene.gaussians.num_gaussians, float(terms["total"])))
        return done == 3

    result = Trainer(cfg, [ImageSource(dataset)], tmp_path / "run", show_progress=False).run(on_step=stop_at_three)
    assert [done for done, _, _ in seen] == [1, 2, 3] and all(n == 300 for _, n, _ in seen)
    assert result.steps == 3 and [h["step"] for h in result.history] == [3]
    assert result.final_loss == pytest.approx(seen[-1][2])
    summary = json.loads((tmp_path / "run" / "train_summary.json").read_text())
    assert summary["steps"] == 3 and (tmp_path / "run" / "model.safetensors").is_file()
    # the same six steps from a given scene, in memory: nothing is written and the scene trains in place
    straight = Trainer(cfg, [ImageSource(dataset)], tmp_path / "full", show_progress=False)
    straight.run()
    in_memory = Trainer(cfg, [ImageSource(dataset)], None, show_progress=False)
    scene = in_memory.build_scene()
    in_memory.run(scene=scene)
    assert in_memory.scene is scene
    assert torch.equal(scene.gaussians.means, straight.scene.gaussians.means)
    assert not (tmp_path / "None").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["full", "run"]
    with pytest.raises(ValueError, match="resuming needs a run_dir"):
        in_memory.run(resume=True)


def test_visual_hull_from_the_generated_views_too(capture):
    """``hull_masks=all`` carves the initial hull with every source's views (here the capture's own views 2-5
    standing in for generated ones): a tighter hull around the analytic sphere (radius 0.5) than 2 real views
    give; ``real`` ignores the extra views (the same points as training on the real images alone)."""
    dataset = OLATDataset(capture)
    real = dataset.subset([i for i, obs in enumerate(dataset.observations) if obs.view < 2])
    extra = dataset.subset([i for i, obs in enumerate(dataset.observations) if obs.view >= 2])

    def initial_means(hull_masks: str, sources: list[ImageSource]) -> torch.Tensor:
        cfg = make_config("diamond", overrides={**TINY, "num_gaussians": 2000, "hull_masks": hull_masks})
        trainer = Trainer(cfg, sources, None, show_progress=False)
        means = trainer.build_scene().gaussians.means.detach()
        assert trainer.init_source == "visual_hull"
        return means

    only_real = initial_means("real", [ImageSource(real)])
    assert torch.equal(initial_means("real", [ImageSource(real), ImageSource(extra, 0.5)]), only_real)
    carved = initial_means("all", [ImageSource(real), ImageSource(extra, 0.5)])
    excess = {name: (means.norm(dim=-1) - 0.5).clamp_min(0).mean() for name, means in
              (("real", only_real), ("all", carved))}
    assert excess["all"] < 0.5 * excess["real"]
    with pytest.raises(ValueError, match="gaussians.hull_masks"):
        make_config("diamond", overrides={"hull_masks": "some"})


def test_densification_changes_the_gaussian_count(capture, tmp_path):
    cfg = make_config("sss3dgs", overrides={**TINY, "iterations": 6, "densification_interval": 3,
                                            "densify_grad_threshold": 1e-7})
    result = Trainer(cfg, [ImageSource(OLATDataset(capture))], tmp_path / "run", show_progress=False).run()
    assert result.num_gaussians > 300


def test_opacities_reset_every_interval_while_densifying(capture):
    """Every opacity is clamped to ``2 prune_opa`` after step 5 (``opacity_reset_interval`` 5) and not after step
    10, which comes after densification stops (gsplat 1.5.3's ``DefaultStrategy`` never resets: gsplat#776)."""
    cfg = make_config("sss3dgs", overrides={**TINY, "iterations": 11, "densify_until_iter": 8})
    ceiling = 2.0 * cfg.densify.prune_opa
    highest = {}

    def record(done, scene, terms):
        highest[done - 1] = float(scene.gaussians.opacities.detach().max())

    Trainer(cfg, [ImageSource(OLATDataset(capture))], None, show_progress=False).run(on_step=record)
    assert highest[4] > 5 * ceiling and highest[5] == pytest.approx(ceiling)
    assert ceiling < highest[9] < highest[10]


def test_cli_train_eval_render_export(capture, tmp_path, capsys):
    previous_umask = os.umask(0o027)
    try:
        _train_eval_render_export(capture, tmp_path, capsys)
    finally:
        os.umask(previous_umask)
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    folders = [p for p in tmp_path.rglob("*") if p.is_dir()]
    assert {p.suffix for p in files} >= {".json", ".safetensors", ".png", ".gif", ".ply", ".csv"}
    assert {p.relative_to(tmp_path).as_posix(): oct(stat.S_IMODE(p.stat().st_mode)) for p in files
            if stat.S_IMODE(p.stat().st_mode) != 0o640} == {}
    assert {p.relative_to(tmp_path).as_posix() for p in folders if stat.S_IMODE(p.stat().st_mode) != 0o750} == set()


def _train_eval_render_export(capture, tmp_path, capsys):
    run = tmp_path / "run"
    sets = [arg for key, value in TINY.items() for arg in ("--set", f"{key}={value}")]
    main(["train", "--data", str(capture), "--out", str(run), "--regime", "views=50%,lights=all",
          "--iterations", "3", "--quiet", *sets])
    regime = json.loads((run / "regime.json").read_text())
    assert len(regime["views"]) == 3 and regime["images"] == 9
    assert json.loads((run / "config.json").read_text())["schedule"]["iterations"] == 3
    capsys.readouterr()
    main(["eval", "--run", str(run), "--data", str(capture), "--split", "test", "--json"])
    metrics = json.loads(capsys.readouterr().out)
    assert {"psnr", "ssim", "lpips", "masked_psnr", "mask_iou", "images"} <= set(metrics)
    assert metrics["lpips"] is None and metrics["images"] == 4
    assert (run / "eval_test" / "per_image.csv").read_text().count("\n") == 5
    assert (run / "eval_test" / "comparison.png").is_file() and (run / "eval_test" / "decomposition.png").is_file()
    main(["render", "--run", str(run), "--out", str(tmp_path / "frames"), "--views", "0", "1",
          "--roughness", "0.2", "--light", "0", "0", "4", "4", "0", "0"])
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["frame_0000.png", "frame_0001.png"]
    main(["render", "--run", str(run), "--out", str(tmp_path / "orbit"), "--orbit", "3", "--size", "12"])
    assert (tmp_path / "orbit" / "orbit.gif").is_file()
    with pytest.raises(SystemExit):
        main(["render", "--run", str(run), "--out", str(tmp_path / "orbit2"), "--orbit", "3", "--video", "o.avi"])
    assert "expected a file name ending in .gif or .mp4" in capsys.readouterr().err
    assert not (tmp_path / "orbit2").exists()  # refused before rendering
    main(["export", "--run", str(run), "--ply", str(tmp_path / "scene.ply")])
    scene, _ = load_scene(run)
    assert import_ply(tmp_path / "scene.ply").num_gaussians == scene.gaussians.num_gaussians


def test_unified_lattice_maps_shared_and_new_cameras(capture, tmp_path):
    from diamond_sss.training.lattice import unify_lattices

    real = OLATDataset(capture)
    extra_root = tmp_path / "generated"
    make_capture(extra_root, views=6, lights=3, size=16)  # the same lattice ...
    make_capture(extra_root / "new", views=2, lights=3, size=16, camera_offset=1.1)  # ... and two new cameras
    same = OLATDataset(extra_root)
    new = OLATDataset(extra_root / "new")
    union = unify_lattices([real, same.subset([5, 9]), new])
    assert union.view_maps[0] == list(range(6)) and union.view_maps[1] == list(range(6))
    assert union.view_maps[2] == [6, 7] and union.num_views == 8
    assert union.light_maps[2] == [0, 1, 2] and union.light_positions.shape == (3, 3)
    assert torch.allclose(union.viewmats[7], new.viewmats[1])
    cfg = make_config("diamond", overrides={**TINY, "iterations": 2, "densify": False})
    trainer = Trainer(cfg, [ImageSource(real), ImageSource(new, 0.5)], tmp_path / "run", show_progress=False)
    trainer.run()
    assert set(trainer.view_silhouettes) == set(range(8))


def test_the_mlp_learning_rate_warms_up_then_decays(capture, tmp_path):
    cfg = make_config("diamond", overrides={**TINY, "sss_lr": 0.004, "sss_lr_warmup_steps": 4, "lr_decay_step": 8,
                                            "lr_decay_factor": 0.5, "densify": False})
    trainer = Trainer(cfg, [ImageSource(OLATDataset(capture))], tmp_path / "run", show_progress=False)
    optimizers = trainer.build_optimizers(trainer.build_scene())
    rates = []
    for step in (0, 1, 3, 7, 8):
        trainer.set_learning_rates(optimizers, step)
        rates.append(optimizers["mlp"].param_groups[0]["lr"])
    assert rates == pytest.approx([0.001, 0.002, 0.004, 0.004, 0.002])
    assert optimizers["light"].param_groups[0]["lr"] == pytest.approx(0.5 * cfg.lr.light)  # not warmed up


@pytest.mark.parametrize("photometric", [True, False])
def test_the_sh_visibility_learns_from_the_photometric_loss_only_when_asked(capture, photometric):
    cfg = make_config("diamond", overrides={**TINY, "sss_visibility_gradient": photometric})
    dataset = OLATDataset(capture)
    trainer = Trainer(cfg, [ImageSource(dataset)], None, show_progress=False)
    built = trainer.build_scene()
    resumed = scene_from_tensors(scene_tensors(built), cfg.shading)  # as a resumed run rebuilds it
    for scene in (built, resumed):
        sh = scene.gaussians.params["visibility_sh"]
        camera, light = dataset.cameras[0], dataset.lights[0]
        scene.render(camera.w2c[None], camera.K[None], camera.width, camera.height, light.position[None],
                     light.intensity[None]).radiance.sum().backward()
        assert (sh.grad is not None and sh.grad.abs().sum() > 0) == photometric
        sh.grad = None
        trainer.raytrace_term(scene, light.position[None], step=0).backward()
        assert sh.grad.abs().sum() > 0  # the ray-traced term trains it either way


def test_a_run_is_not_resumed_on_other_images(capture, tmp_path):
    """A finished run folder resumed with another capture would be reported as the model of images it never saw: it
    is refused, naming both, and what the folder records is left as it was."""
    from diamond_sss.training.run import train_run

    config = make_config("sss3dgs", overrides={**TINY, "iterations": 2})
    run = tmp_path / "run"
    train_run(capture, run, config, regime="views=2,lights=1", resume=True, show_progress=False)
    recorded = (run / "data.json").read_bytes(), (run / "model.safetensors").read_bytes()
    other = make_capture_with_test_split(tmp_path / "other", views=6, lights=3, size=16, camera_offset=0.3)
    with pytest.raises(ValueError, match=r"run was trained on other images \(.*capture.*, regime 'views=2,lights=1'\) "
                                         r"than .*other with regime 'views=2,lights=1'"):
        train_run(other, run, config, regime="views=2,lights=1", resume=True, show_progress=False)
    with pytest.raises(ValueError, match=r"trained on other images .* with regime 'views=3,lights=1'"):
        train_run(capture, run, config, regime="views=3,lights=1", resume=True, show_progress=False)
    assert ((run / "data.json").read_bytes(), (run / "model.safetensors").read_bytes()) == recorded
    again = train_run(capture, run, config, regime="views=2,lights=1", resume=True, show_progress=False)
    assert again.steps == 2  # the same images: the finished run is reused
    for damaged, message in (("{not json", r"data.json: damaged or invalid JSON"),
                             ("[1, 2]", r"data.json: expected a JSON object with the keys data, regime")):
        (run / "data.json").write_text(damaged)
        with pytest.raises(ValueError, match=message):
            train_run(capture, run, config, regime="views=2,lights=1", resume=True, show_progress=False)
        assert (run / "data.json").read_text() == damaged  # named, and left as it was


def test_a_run_trains_on_its_cpu_threads_and_gives_the_process_its_own_back(capture, tmp_path):
    """runtime.cpu_threads holds during the run and not after it (the diffusion stages after a preliminary
    reconstruction ran on its 1 thread: 42.7 s against 25.2 s on 2 cores)."""
    config = make_config("sss3dgs", overrides={**TINY, "iterations": 2, "cpu_threads": 1})
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        during = []
        Trainer(config, [ImageSource(OLATDataset(capture))], tmp_path / "run", show_progress=False).run(
            on_step=lambda *args: during.append(torch.get_num_threads()))
        assert during == [1, 1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
