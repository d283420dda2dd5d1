"""Render repair (issue 59): the model's identity start, its inputs, the training pairs, exact resume, and
``run --augment repair`` end to end, on an analytic capture with a tiny model."""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from repo_scripts import load_script
from safetensors.torch import save_file

from diamond_sss.cli.main import main
from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture_with_test_split
from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.data.export import export_regime
from diamond_sss.data.images import read_image_array, write_png
from diamond_sss.diffusion.common.manifest import GeneratedImage, read_image_manifest
from diamond_sss.diffusion.relight.light import light_code
from diamond_sss.diffusion.repair.config import (
    IMAGE_CHANNELS,
    INPUT_CHANNELS,
    RepairModelConfig,
    RepairTrainConfig,
)
from diamond_sss.diffusion.repair.data import (
    RepairPairs,
    read_pair_metadata,
    shrunk_pair,
    target_image,
    write_pairs,
)
from diamond_sss.diffusion.repair.inputs import RepairInputs
from diamond_sss.diffusion.repair.model import RepairModel
from diamond_sss.diffusion.repair.train import train_repair, validation
from diamond_sss.errors import DataError
from diamond_sss.pipeline.config import REPAIR_ROUNDS
from diamond_sss.pipeline.run import (
    PipelineConfig,
    checked_config,
    mask_area_ratio,
    previous_round_folder,
    run_pipeline,
)
from diamond_sss.runs.folder import load_scene
from diamond_sss.training.run import train_from_preset
from diamond_sss.utils.io import read_json

TRAIN = {"num_gaussians": 200, "batch_size": 1, "lambda_lpips": 0.0, "iterations": 2, "raytrace_gaussians": 32,
         "mv_pixels_per_pair": 16, "log_every": 1, "device": "cpu"}
TINY = RepairModelConfig(block_out_channels=(8, 16), norm_num_groups=4, resolution=16)
REGIME = "views=2,lights=1"


def tiny_model(seed: int = 0) -> RepairModel:
    torch.manual_seed(seed)
    return RepairModel(TINY)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    data = tmp_path_factory.mktemp("capture")
    make_capture_with_test_split(data, views=6, lights=3, size=16)
    run = tmp_path_factory.mktemp("run") / "prelim"
    train_from_preset(data, run, regime=REGIME, overrides=TRAIN, show_progress=False)
    pairs = write_pairs(run, tmp_path_factory.mktemp("pairs") / "prelim.safetensors", most=6, show_progress=False)
    model = tiny_model()
    with torch.no_grad():  # a repair model that changes the render: its last layer away from zero
        model.unet.conv_out.weight.normal_(0.0, 0.05)
    return data, run, pairs, model.save(tmp_path_factory.mktemp("repair"))


def test_an_untrained_model_returns_the_render_at_any_size():
    model = tiny_model()
    inputs = torch.rand(2, INPUT_CHANNELS, 18, 22) * 1.2  # sides not multiples of 2: padded and cropped back
    output = model(inputs)
    assert output.shape == (2, 4, 18, 22)
    assert torch.equal(output, inputs[:, :4].clamp(0, 1))
    output.sum().backward()  # the zero last layer still receives a gradient: training moves it
    assert model.unet.conv_out.weight.grad.abs().sum() > 0


def test_a_saved_model_loads_to_the_same_outputs(tmp_path, setup):
    model = RepairModel.load(setup[3])
    inputs = torch.rand(1, INPUT_CHANNELS, 16, 16)
    with torch.no_grad():
        first = model(inputs)
    assert not torch.equal(first, inputs[:, :4].clamp(0, 1))
    again = RepairModel.load(model.save(tmp_path / "copy"))
    with torch.no_grad():
        assert torch.equal(again(inputs), first)
    (tmp_path / "copy" / "config.json").write_text(json.dumps({"model": "nvs", "config": {}}))
    with pytest.raises(ValueError, match="holds a 'nvs' model, not a 'repair' one"):
        RepairModel.load(tmp_path / "copy")


def test_the_inputs_hold_the_render_the_real_image_warped_and_the_light_code(setup):
    data, run, _, _ = setup
    dataset = OLATDataset(data, "train")
    seen = read_json(run / "regime.json")["observations"]
    builder = RepairInputs(load_scene(run)[0].eval(), dataset, dataset, seen)
    obs = dataset.observations[seen[0]]
    inputs, render = builder.target(obs.view, obs.light)
    assert inputs.shape == (INPUT_CHANNELS, 16, 16)
    assert torch.allclose(inputs[:3], linear_to_srgb(render.radiance[0].clamp(0, 1)).permute(2, 0, 1))
    assert torch.allclose(inputs[3], render.gbuffer.alpha[0, ..., 0])
    # a real image warped into its own camera lands on itself, wherever the render has a surface
    valid = inputs[12] > 0
    assert valid.float().mean() > 0.2
    real = linear_to_srgb(dataset.load(seen[0]).rgb).permute(2, 0, 1)
    assert torch.allclose(inputs[9:12][:, valid], real[:, valid], atol=1e-4)
    camera, light = dataset.cameras[obs.view], dataset.lights[obs.light]
    code = light_code(light.position, camera.w2c, dataset.bounds.center, dataset.bounds.radius)
    assert torch.allclose(inputs[13:, 0, 0], code.float()) and torch.allclose(inputs[13:, 15, 9], code.float())
    # under a light no real image has, nothing is warped
    unlit = next(light for light in range(dataset.num_lights) if light not in builder.real_of_light)
    assert builder.source(obs.view, unlit) is None
    assert not builder.target(obs.view, unlit)[0][9:13].any()


def test_a_larger_capture_is_repaired_at_the_models_size(setup, tmp_path):
    data, run, _, model = setup
    dataset = OLATDataset(data, "train")
    seen = read_json(run / "regime.json")["observations"]
    builder = RepairInputs(load_scene(run)[0].eval(), dataset, dataset, seen, size=8)
    obs = dataset.observations[seen[0]]
    inputs, render = builder.target(obs.view, obs.light)
    assert inputs.shape == (INPUT_CHANNELS, 8, 8) and render.radiance.shape == (1, 8, 8, 3)
    camera = dataset.cameras[obs.view]
    assert torch.allclose(builder.camera(obs.view)[1][:2], camera.K[:2] / 2)  # a 16-px camera at 8 px
    assert inputs[12].any()  # the full-size real image still warps into the smaller target
    small = RepairModel.load(model)
    object.__setattr__(small, "config", RepairModelConfig(**{**small.config.__dict__, "resolution": 8}))
    small.save(tmp_path / "small")
    cfg = PipelineConfig(augment=("repair",), repair_model=str(tmp_path / "small"), nvs_views=2, relight_lights=1,
                         min_silhouette_iou=0.0, min_mask_fraction=0.0)
    result = run_pipeline(data, tmp_path / "run", regime=REGIME, overrides={**TRAIN, "lambda_dssim": 0.0}, config=cfg,
                          show_progress=False)  # no SSIM on 8-px images
    repaired = OLATDataset(tmp_path / "run" / "synthetic", "train")
    assert result["synthetic_images"] == 6 and {repaired.cameras[o.view].width for o in repaired.observations} == {8}


def test_pairs_are_the_unseen_images_against_the_truth(setup, tmp_path):
    data, run, pairs_file, _ = setup
    metadata = read_pair_metadata(pairs_file)
    assert metadata["pairs"] == "6" and metadata["data"] == str(data.resolve())
    pairs = RepairPairs.read([pairs_file])
    dataset = OLATDataset(data, "train")
    seen = set(read_json(run / "regime.json")["observations"])
    targets = [target_image(dataset, i) for i in range(len(dataset.observations)) if i not in seen]
    assert any(torch.allclose(pairs.targets[0], t, atol=1e-3) for t in targets)  # float16 storage
    with pytest.raises(DataError, match="no regime.json"):
        write_pairs(tmp_path, tmp_path / "x.safetensors")


def _twin(data: Path, out: Path, edit) -> Path:
    """A copy of capture ``data`` whose train transforms went through ``edit`` (same images)."""
    shutil.copytree(data, out)
    path = out / "transforms_train.json"
    transforms = json.loads(path.read_text())
    edit(transforms)
    path.write_text(json.dumps(transforms))
    return out


def test_pairs_at_a_twin_lattice_are_made_at_its_cameras_and_checked_against_the_capture(setup, tmp_path):
    data, run, _, _ = setup
    plain = write_pairs(run, tmp_path / "plain.safetensors", most=4, show_progress=False)
    same = write_pairs(run, tmp_path / "same.safetensors", lattice=data, most=4, show_progress=False)
    assert torch.equal(RepairPairs.read([same]).inputs, RepairPairs.read([plain]).inputs)
    zoomed = _twin(data, tmp_path / "zoomed", lambda t: t.update(camera_angle_x=t["camera_angle_x"] * 0.6))
    framed = write_pairs(run, tmp_path / "framed.safetensors", lattice=zoomed, most=4, show_progress=False)
    assert read_pair_metadata(framed)["lattice"] == str(zoomed.resolve())
    near, far = RepairPairs.read([framed]), RepairPairs.read([plain])
    assert torch.equal(near.targets, far.targets)  # the same images, drawn at the same unseen (view, light) pairs
    assert near.inputs[:, 3].sum() > 1.5 * far.inputs[:, 3].sum()  # the render's alpha: the object zoomed in
    def shift_camera_2(transforms: dict) -> None:
        transforms["frames"][2]["transform_matrix"][0][3] += 0.5

    moved = _twin(data, tmp_path / "moved", shift_camera_2)
    with pytest.raises(DataError, match=r"moved/transforms_train\.json \(the lattice twin of .*\): camera centre 2 "
                                        r"is 0\.5 away"):
        write_pairs(run, tmp_path / "x.safetensors", lattice=moved, show_progress=False)
    fewer = _twin(data, tmp_path / "fewer", lambda t: t.update(frames=t["frames"][:4]))
    with pytest.raises(DataError, match=r"fewer/transforms_train\.json .*: 4 views and 3 lights, the capture has 6 and 3"):
        write_pairs(run, tmp_path / "x.safetensors", lattice=fewer, show_progress=False)
    assert not (tmp_path / "x.safetensors").exists()


def test_batches_crop_the_same_window_of_input_and_target():
    rows, cols = torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="ij")
    pattern = (rows * 10 + cols)[None, None]
    pairs = RepairPairs(pattern.expand(3, INPUT_CHANNELS, 8, 8).clone(), pattern.expand(3, 4, 8, 8).clone(), [])
    inputs, targets = pairs.batch(5, 4, torch.Generator().manual_seed(1))
    assert inputs.shape == (5, INPUT_CHANNELS, 4, 4) and targets.shape == (5, 4, 4, 4)
    for window in inputs[:, 0]:
        top, left = divmod(int(window[0, 0]), 10)
        assert torch.equal(window, pattern[0, 0, top:top + 4, left:left + 4])
    assert torch.equal(inputs[:, :4], targets)


def test_a_shrunk_pair_is_the_area_resampled_image_placed_alike_in_input_and_target():
    inputs = torch.zeros(INPUT_CHANNELS, 8, 8)
    inputs[:IMAGE_CHANNELS, 2:6, 2:6] = 1.0  # a 4 x 4 object in the middle
    inputs[IMAGE_CHANNELS:] = torch.arange(INPUT_CHANNELS - IMAGE_CHANNELS, dtype=torch.float32)[:, None, None]
    targets = inputs[:4].clone() * 0.5
    shrunk, target = shrunk_pair(inputs, targets, 0.5, torch.Generator().manual_seed(3))
    assert shrunk.shape == inputs.shape and target.shape == targets.shape
    covered = shrunk[0] > 0  # the 4 x 4 image the 8 x 8 one became holds the object as 2 x 2 pixels of value 1
    assert int(covered.sum()) == 4 and torch.equal(shrunk[:IMAGE_CHANNELS][:, covered], torch.ones(IMAGE_CHANNELS, 4))
    assert torch.equal(target[:, covered], torch.full((4, 4), 0.5)) and int((target[0] > 0).sum()) == 4
    assert torch.equal(shrunk[IMAGE_CHANNELS:], inputs[IMAGE_CHANNELS:])  # the light code stays constant
    rows, cols = covered.nonzero().unbind(1)
    assert (rows.max() - rows.min(), cols.max() - cols.min()) == (1, 1)
    edge = shrunk_pair(inputs, targets, 0.75, torch.Generator().manual_seed(0))[0][0]  # 6 x 6: partial pixels
    assert edge.sum() == pytest.approx(16 * 0.75**2) and 0 < edge[edge > 0].min() < 1
    pairs = RepairPairs(inputs[None].expand(3, -1, -1, -1).clone(), targets[None].expand(3, -1, -1, -1).clone(), [])
    zoomed, _ = pairs.batch(6, 0, torch.Generator().manual_seed(1), zoom_out=0.5)
    assert all(0.25 * 16 - 1e-5 <= float(image.sum()) <= 16 + 1e-5 for image in zoomed[:, 0])
    assert not torch.equal(zoomed[:, 0], inputs[0].expand(6, -1, -1))
    with pytest.raises(ValueError, match=r"zoom_out must be in \(0, 1\]"):
        RepairTrainConfig(zoom_out=0.0)


def test_training_lowers_the_error_and_resumes_exactly(setup, tmp_path):
    _, _, pairs_file, _ = setup
    config = RepairTrainConfig(steps=3, batch_size=2, crop=8, checkpoint_every=1, log_every=1, validation_files=0,
                               warmup_steps=0, learning_rate=1e-2, ema_decay=0.0)
    straight = train_repair([pairs_file], tmp_path / "straight", config, model=tiny_model(), log=lambda _: None)
    stopped = RepairTrainConfig(**{**config.__dict__, "time_limit_s": 0.0})
    train_repair([pairs_file], tmp_path / "resumed", stopped, model=tiny_model(), log=lambda _: None)
    log = (tmp_path / "resumed" / "train_log.jsonl").read_text().splitlines()
    assert [json.loads(line)["step"] for line in log] == [1]
    resumed = train_repair([pairs_file], tmp_path / "resumed", config, model=tiny_model(seed=5), log=lambda _: None)
    a, b = RepairModel.load(straight).state_dict(), RepairModel.load(resumed).state_dict()
    assert all(torch.allclose(a[k], b[k], atol=1e-6) for k in a)
    longer = RepairTrainConfig(**{**config.__dict__, "steps": 40, "crop": 0})
    trained = RepairModel.load(train_repair([pairs_file], tmp_path / "longer", longer, model=tiny_model(),
                                            log=lambda _: None))
    pairs = RepairPairs.read([pairs_file])
    with torch.no_grad():
        before = (tiny_model()(pairs.inputs) - pairs.targets).abs().mean()
        after = (trained(pairs.inputs) - pairs.targets).abs().mean()
    assert after < before
    with pytest.raises(ValueError, match="all held out for validation"):
        train_repair([pairs_file], tmp_path / "none", RepairTrainConfig(validation_files=1))


def test_run_with_augment_repair_makes_the_images_the_paper_stages_would(setup, tmp_path, capsys, monkeypatch):
    import diamond_sss.pipeline.run as pipeline_run

    data, _, _, model = setup
    weights, train_run = {}, pipeline_run.train_run

    def recorded(data, out, config, **kwargs):
        weights[out.name] = [source.weight for source in kwargs.get("extra_sources", ())]
        return train_run(data, out, config, **kwargs)

    monkeypatch.setattr(pipeline_run, "train_run", recorded)
    cfg = PipelineConfig(augment=("repair",), repair_model=str(model), nvs_views=2, relight_lights=1,
                         min_silhouette_iou=0.0, min_mask_fraction=0.0, synthetic_weight=0.75, min_real_share=0.0,
                         min_round_mask_area=0.0)
    result = run_pipeline(data, tmp_path, regime=REGIME, overrides=TRAIN, config=cfg)
    assert weights["final"] == [0.75]  # repaired images weigh synthetic_weight, as generated ones
    printed = capsys.readouterr()
    assert re.search(r"repair: 100%\|[^|]*\| 1/1 ", printed.err)
    assert re.search(r"repair: the generated masks cover \d+\.\d% of the previous round's area \(6 images\), at "
                     r"least min_round_mask_area \(0%\): this round trains; the threshold was measured with the "
                     r"shipped repair model, not --repair-model's", printed.out)
    assert "round of another pipeline" not in printed.out  # round 1's own preliminary reconstruction
    manifest = json.loads((tmp_path / "pipeline.json").read_text())
    assert list(manifest["stages"]) == ["prelim", "repair", "final", "eval"]
    assert set(manifest["inputs"]["model_hashes"]) == {"repair"}
    # as nvs + relight: 2 new views under the 1 real light, then the 4 views with an image each relit to 1 more light
    assert manifest["stages"]["repair"]["images"] == 6
    # the second round (the default) compares its masks with the first round's; the first has none to compare with
    first = json.loads((tmp_path / "round1" / "pipeline.json").read_text())["stages"]["repair"]
    assert "mask_area_vs_previous_round" not in first
    ratio = mask_area_ratio(repaired_images_in(tmp_path), repaired_images_in(tmp_path / "round1"))[0]
    assert manifest["stages"]["repair"]["mask_area_vs_previous_round"] == pytest.approx(ratio, abs=1e-4) and ratio > 0
    assert result["synthetic_images"] == 6 and result["real_images"] == 2
    repaired = OLATDataset(tmp_path / "synthetic", "train")
    assert len(repaired) == 6 and {"psnr", "mask_iou"} <= set(result)


def test_a_round_whose_masks_shrank_keeps_the_previous_rounds_reconstruction(setup, tmp_path, capsys, monkeypatch):
    import diamond_sss.pipeline.run as pipeline_run

    data, _, _, model = setup
    trained, train_run = [], pipeline_run.train_run

    def recorded(data, out, config, **kwargs):
        trained.append(out.relative_to(tmp_path))
        return train_run(data, out, config, **kwargs)

    monkeypatch.setattr(pipeline_run, "train_run", recorded)
    ratios = {}

    def ratio(current, previous):
        ratios[len(ratios)] = (found := mask_area_ratio(current, previous))
        return (0.5 * found[0], found[1])  # round 2's masks at half of their area: under the threshold

    monkeypatch.setattr(pipeline_run, "mask_area_ratio", ratio)
    cfg = PipelineConfig(augment=("repair",), repair_model=str(model), nvs_views=2, relight_lights=1, rounds=3,
                         min_silhouette_iou=0.0, min_mask_fraction=0.0, min_round_mask_area=0.9)
    result = run_pipeline(data, tmp_path, regime=REGIME, overrides=TRAIN, config=cfg)
    # only round 1 trains a final reconstruction; rounds 2 and 3 copy it (round 3 because round 2 kept)
    assert trained == [Path("round1/prelim"), Path("round1/final")] and len(ratios) == 1
    printed = capsys.readouterr().out
    assert re.search(r"masks cover \d+\.\d% of the previous round's area \(6 images\), under min_round_mask_area "
                     r"\(90%\).*this round keeps the previous round's final reconstruction", printed)
    assert "kept the final reconstruction of the round before it; so does this round" in printed
    rounds = [json.loads((folder / "pipeline.json").read_text())["stages"]
              for folder in (tmp_path / "round1", tmp_path / "round2", tmp_path)]
    assert rounds[1]["final"]["kept"] == str(tmp_path / "round1" / "final")
    assert rounds[2]["final"]["kept"] == str(tmp_path / "round2" / "final")
    assert rounds[1]["repair"]["mask_area_vs_previous_round"] == pytest.approx(0.5 * ratios[0][0], abs=1e-4)
    assert "mask_area_vs_previous_round" not in rounds[2]["repair"]  # not compared: round 2 had stopped the rounds
    for key in ("real_images", "synthetic_images", "real_share"):  # the kept reconstruction's counts
        assert rounds[2]["final"][key] == rounds[0]["final"][key] == result[key]
    first, last = (tmp_path / "round1" / "final" / "model.safetensors"), (tmp_path / "final" / "model.safetensors")
    assert first.read_bytes() == last.read_bytes()
    assert result["psnr"] == pytest.approx(rounds[0]["eval"]["psnr"], abs=1e-9)
    assert result["round_psnr"] == pytest.approx([result["psnr"]] * 3)
    trained.clear()
    run_pipeline(data, tmp_path / "other", regime=REGIME, overrides=TRAIN,
                 config=replace(cfg, rounds=1, prelim_run=str(tmp_path / "round1" / "final")))
    # another pipeline's round is this one's preliminary reconstruction, not a previous round: compared with nothing
    assert trained == [Path("other/final")] and len(ratios) == 1
    assert "is a round of another pipeline, not a previous round of this one: no mask area compared, this round " \
           "trains" in capsys.readouterr().out
    assert "mask_area_vs_previous_round" not in json.loads((tmp_path / "other" / "pipeline.json").read_text())[
        "stages"]["repair"]
    with pytest.raises(ValueError, match=r"'min_round_mask_area' \(--min-round-mask-area\) must be in \[0, 1\]"):
        checked_config(PipelineConfig(augment=("repair",), min_round_mask_area=1.5))


def test_the_previous_round_is_the_round_before_in_the_same_pipeline_only(tmp_path):
    run = tmp_path / "run"
    assert previous_round_folder(run, run / "round2" / "final") == (run / "round2").resolve()  # the last round
    assert previous_round_folder(run / "round2", run / "round1" / "final") == (run / "round1").resolve()
    assert previous_round_folder(run / "round3", run / "round1" / "final") is None  # not the round before
    assert previous_round_folder(run, run / "prelim") is None  # a first round's own preliminary reconstruction
    assert previous_round_folder(run, tmp_path / "other" / "final") is None  # another pipeline's final
    assert previous_round_folder(run, tmp_path / "other" / "round1" / "final") is None
    assert previous_round_folder(run, run / "roundx" / "final") is None


def test_repair_is_refused_beside_the_paper_stages_or_without_a_model(setup, tmp_path):
    data = setup[0]
    with pytest.raises(ValueError, match="repair takes the place of nvs and relight"):
        run_pipeline(data, tmp_path / "a", regime=REGIME, overrides=TRAIN,
                     config=PipelineConfig(augment=("nvs", "repair")))
    with pytest.raises(FileNotFoundError, match="no repair model in .*pass --repair-model"):
        run_pipeline(data, tmp_path / "b", regime=REGIME, overrides=TRAIN,
                     config=PipelineConfig(augment=("repair",), repair_model=str(tmp_path / "missing")))


def test_the_command_line_writes_pairs_and_trains(setup, tmp_path, capsys):
    _, run, _, _ = setup
    main(["repair-data", "--run", str(run), "--out", str(tmp_path / "pairs"), "--most", "2", "--quiet"])
    pairs = tmp_path / "pairs" / "prelim.safetensors"
    assert read_pair_metadata(pairs)["pairs"] == "2"
    main(["repair-data", "--run", str(run), "--out", str(tmp_path / "pairs"), "--quiet"])
    assert "exists, kept" in capsys.readouterr().out
    main(["repair-train", "--pairs", str(pairs), str(pairs), "--out", str(tmp_path / "train"), "--steps", "2",
          "--batch-size", "2", "--crop", "8", "--block-out-channels", "8", "16", "--norm-num-groups", "4", "--quiet"])
    validation = read_json(tmp_path / "train" / "validation.json")
    assert validation["pairs"] == 2 and validation["repaired_psnr"] > 0 and validation["render_psnr"] > 0


def test_the_quality_benchmark_scores_the_renders_and_their_repairs(setup, tmp_path, monkeypatch, capsys):
    _, run, _, model = setup
    benchmark = load_script("benchmarks/repair_quality.py", "repair_quality_benchmark")
    monkeypatch.setattr("sys.argv", ["repair_quality.py", "--model", str(model), "--runs", str(run), "--most", "3",
                                     "--pairs-dir", str(tmp_path / "pairs"), "--results", str(tmp_path / "out")])
    benchmark.main()
    row = json.loads((tmp_path / "out" / "repair_quality.json").read_text())["rows"][0]
    pairs = RepairPairs.read(list((tmp_path / "pairs").glob("*.safetensors")))
    assert row["pairs"] == 3 and row == {**row, **validation(RepairModel.load(model), pairs)}
    assert "| reconstruction | capture | pairs | render | repaired |" in capsys.readouterr().out


def test_a_capture_of_only_its_sparse_images_gets_new_cameras_and_lights(setup, tmp_path):
    """Three images of three views under three lights (an incomplete lattice): relighting alone would find targets
    on it, but repair makes new views too, so the cameras and lights are placed around the real ones."""
    data, _, _, model = setup
    sparse = export_regime(data, tmp_path / "sparse", "images=3", seed=0).out
    real = OLATDataset(sparse, "train")
    assert len(real) == 3 and len(real) < real.num_views * real.num_lights
    cfg = PipelineConfig(augment=("repair",), repair_model=str(model), rig_views=2, rig_lights=1, nvs_views=0,
                         relight_lights=1, min_silhouette_iou=0.0, min_mask_fraction=0.0)
    run_pipeline(sparse, tmp_path / "run", regime="all", overrides=TRAIN, config=cfg, show_progress=False)
    manifest = json.loads((tmp_path / "run" / "pipeline.json").read_text())
    assert manifest["inputs"]["lattice"] == "sampled"
    views = {item["view"] for item in json.loads((tmp_path / "run" / "repair" / "manifest.json").read_text())}
    assert views >= {real.num_views, real.num_views + 1}  # the two placed cameras


def test_repair_runs_two_rounds_unless_told_and_the_paper_stages_one():
    assert checked_config(PipelineConfig(augment=("repair",))).rounds == REPAIR_ROUNDS == 2
    assert checked_config(PipelineConfig(augment=("repair",), rounds=1)).rounds == 1
    assert checked_config(PipelineConfig()).rounds == 1 and checked_config(PipelineConfig(augment=())).rounds == 1


def test_bad_pair_files_and_run_folders_are_named(setup, tmp_path):
    _, run, pairs_file, _ = setup
    damaged = tmp_path / "damaged.safetensors"
    damaged.write_bytes(pairs_file.read_bytes()[:200])
    for read in (lambda p: RepairPairs.read([p]), read_pair_metadata):
        with pytest.raises(DataError, match=r"damaged\.safetensors: damaged or truncated"):
            read(damaged)
        with pytest.raises(DataError, match=r"missing\.safetensors: .*missing"):
            read(tmp_path / "missing.safetensors")
    pairs = RepairPairs.read([pairs_file])
    nan = tmp_path / "nan.safetensors"
    save_file({"inputs": pairs.inputs.clone().index_fill_(0, torch.tensor([0]), float("nan")).half(),
               "targets": pairs.targets.half()}, str(nan))
    with pytest.raises(DataError, match=r"nan\.safetensors: holds a non-finite value"):
        RepairPairs.read([nan])
    narrow = tmp_path / "narrow.safetensors"
    save_file({"inputs": pairs.inputs[:, :5].contiguous(), "targets": pairs.targets}, str(narrow))
    with pytest.raises(DataError, match=r"narrow\.safetensors: inputs of 5 and targets of 4 channels, expected 23"):
        RepairPairs.read([narrow])
    broken = tmp_path / "broken_run"
    shutil.copytree(run, broken)
    (broken / "regime.json").write_text(json.dumps({"views": [0]}))
    with pytest.raises(DataError, match=r"regime\.json: no 'observations' list"):
        write_pairs(broken, tmp_path / "x.safetensors")
    (broken / "regime.json").write_text("{not json")
    with pytest.raises(DataError, match=r"regime\.json: damaged or invalid JSON"):
        write_pairs(broken, tmp_path / "x.safetensors")
    assert not (tmp_path / "x.safetensors").exists()


def test_the_repair_stage_runs_on_the_idle_cores_says_so_and_makes_the_same_images_on_any_count(setup, tmp_path,
                                                                                                  capsys, monkeypatch):
    import diamond_sss.pipeline.run as pipeline_run

    data, _, _, model = setup
    monkeypatch.setattr(pipeline_run, "idle_cpu_cores", lambda: (1.3, 2))  # another job holds most of a core
    seen, repair_stage = [], pipeline_run.repair_stage

    def counted(ctx):
        seen.append(torch.get_num_threads())
        return repair_stage(ctx)

    monkeypatch.setattr(pipeline_run, "repair_stage", counted)
    threads, images = torch.get_num_threads(), {}
    for name, count in (("idle", None), ("two", 2)):
        cfg = PipelineConfig(augment=("repair",), repair_model=str(model), nvs_views=2, relight_lights=1, rounds=1,
                             min_silhouette_iou=0.0, min_mask_fraction=0.0, generation_threads=count, device="cpu")
        run_pipeline(data, tmp_path / name, regime=REGIME, overrides=TRAIN, config=cfg, show_progress=False)
        folder = tmp_path / name / "repair"
        images[name] = {str(path.relative_to(folder)): read_image_array(path).astype(np.int64)
                        for path in sorted(folder.rglob("*.png"))}
    assert seen == [1, 2] and torch.get_num_threads() == threads  # restored after each stage
    assert "repair: 1 CPU thread (1.3 of 2 cores idle; --generation-threads sets it)" in capsys.readouterr().out
    assert len(images["idle"]) == 12 and images["idle"].keys() == images["two"].keys()  # 6 images, 6 masks
    # another thread count sums in another order: at most one 8-bit level, in at most 1% of the values
    differences = np.concatenate([np.abs(images["idle"][key] - images["two"][key]).ravel() for key in images["idle"]])
    assert differences.max() <= 1 and (differences > 0).mean() <= 0.01
    with pytest.raises(ValueError, match=r"'generation_threads' \(--generation-threads\) must be >= 0"):
        checked_config(PipelineConfig(generation_threads=-1))


def repaired_images_in(run):
    return read_image_manifest(run / "repair" / "manifest.json")


def test_mask_area_ratio_over_the_images_both_rounds_made(tmp_path):
    def made(folder, view, light, pixels):
        mask = np.zeros((4, 4), dtype=np.uint8)
        mask.flat[:pixels] = 255
        folder.mkdir(parents=True, exist_ok=True)
        image = write_png(folder / f"v{view}_l{light}.png", np.zeros((4, 4, 3), dtype=np.uint8))
        return GeneratedImage(view, light, image, write_png(folder / f"v{view}_l{light}_mask.png", mask))

    now = [made(tmp_path / "now", 0, 0, 4), made(tmp_path / "now", 1, 0, 2), made(tmp_path / "now", 2, 0, 16)]
    before = [made(tmp_path / "before", 0, 0, 8), made(tmp_path / "before", 1, 0, 4)]
    assert mask_area_ratio(now, before) == (pytest.approx(6 / 12), 2)  # view 2 has no image in the round before
    assert mask_area_ratio(now, []) is None
    assert mask_area_ratio(now[:1], [made(tmp_path / "empty", 0, 0, 0)]) is None
