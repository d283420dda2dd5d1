"""The DIAMOND-SSS pipeline end to end with tiny random diffusion models on an analytic capture."""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import asdict, replace

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from tiny_models import TINY_NVS, TINY_RELIGHT

from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture, make_capture_with_test_split
from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.data.images import resize_area, to_srgb8, write_png
from diamond_sss.diffusion.nvs.model import NVSConfig, NVSModel
from diamond_sss.diffusion.relight.config import RelightModelConfig
from diamond_sss.diffusion.relight.model import RelightDiffusion
from diamond_sss.pipeline.agreement import agreement_factors, render_errors
from diamond_sss.pipeline.capture import GeneratedImage, write_capture
from diamond_sss.pipeline.run import (
    PipelineConfig,
    PipelineManifest,
    StageRecord,
    changed_inputs,
    compared_inputs,
    listed_changes,
    move_aside_if_changed,
    real_copies,
    run_pipeline,
    spread_subset,
    target_real_share,
)
from diamond_sss.runs.folder import load_scene
from diamond_sss.training.run import train_from_preset
from diamond_sss.training.trainer import ImageSource
from diamond_sss.utils.io import sha256_file, sha256_json

TRAIN = {"num_gaussians": 200, "batch_size": 1, "lambda_lpips": 0.0, "iterations": 2, "raytrace_gaussians": 32,
         "mv_pixels_per_pair": 16, "log_every": 1, "device": "cpu"}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    data = tmp_path_factory.mktemp("capture")
    make_capture_with_test_split(data, views=6, lights=3, size=16)
    torch.manual_seed(0)
    nvs = NVSModel(NVSConfig(**TINY_NVS)).save(tmp_path_factory.mktemp("nvs"))
    relight = RelightDiffusion.from_config(RelightModelConfig(**TINY_RELIGHT)).save(tmp_path_factory.mktemp("rl"))
    return data, nvs, relight, tmp_path_factory.mktemp("cache")


def test_write_capture_keeps_the_lattice(setup, tmp_path):
    data = setup[0]
    real = OLATDataset(data)
    picks = [real.observations[i] for i in (4, 11)]
    path = write_capture(tmp_path, "gen", real, [GeneratedImage(o.view, o.light, o.image_path) for o in picks])
    generated = OLATDataset(tmp_path, "gen")
    assert path.name == "transforms_gen.json"
    assert (generated.num_views, generated.num_lights, len(generated)) == (real.num_views, real.num_lights, 2)
    assert [(o.view, o.light) for o in generated.observations] == [(o.view, o.light) for o in picks]
    assert torch.allclose(generated.viewmats, real.viewmats, atol=1e-5)
    assert torch.allclose(generated.intrinsics, real.intrinsics, atol=1e-4)
    assert torch.equal(generated.load(0).rgb, real.load(4).rgb)
    assert json.loads(path.read_text())["premultiplied_alpha"] is True
    rgba = np.full((real.height, real.width, 4), 255, np.uint8)
    rgba[..., 3], rgba[0, 0, 3] = 128, 0  # colour without coverage at (0, 0): the per-file guess says straight
    write_capture(tmp_path, "edge", real, [GeneratedImage(0, 0, write_png(tmp_path / "edge.png", rgba))])
    assert float(OLATDataset(tmp_path, "edge").load(0).rgb[1, 1, 0]) == 1.0  # as written, not x alpha again
    outside = GeneratedImage(6, 0, picks[0].image_path)
    with pytest.raises(ValueError, match=r"view 6 / light 0 outside the lattice's 6 views x 3 lights"):
        write_capture(tmp_path, "bad", real, [outside])
    assert not (tmp_path / "transforms_bad.json").exists()


def test_target_real_share_grows_with_the_real_images():
    cfg = PipelineConfig()
    assert target_real_share(9, cfg) == 0.5 and target_real_share(30, cfg) == pytest.approx(30 / 39)
    assert target_real_share(30, replace(cfg, generated_as_real=30.0)) == 0.5
    assert target_real_share(30, replace(cfg, min_real_share=0.0)) == 0.0  # given: as it is


def test_real_copies():
    assert real_copies(9, 165, 0.0) == 0 and real_copies(9, 0, 0.5) == 0
    assert real_copies(9, 165, 0.5) == 18  # 19 x 9 = 171 real entries >= 165 synthetic; 18 x 9 = 162 are not
    assert real_copies(10, 10, 0.5) == 0 and real_copies(10, 30, 0.5) == 2
    assert real_copies(10, 30, 0.25) == 0


def test_agreement_factors():
    errors = [0.1, 0.2, 0.4, 0.8]  # median 0.3
    assert agreement_factors(errors, 1.0) == pytest.approx([1.0, 1.0, 0.75, 0.375])
    assert agreement_factors(errors, 2.0) == pytest.approx([1.0, 1.0, 0.5625, 0.140625])
    assert agreement_factors(errors, 0.0) == [1.0] * 4 and agreement_factors([], 1.0) == []
    with pytest.raises(ValueError, match="agreement power must be >= 0"):
        agreement_factors(errors, -1.0)


def test_render_errors_against_the_preliminary_reconstruction(setup, tmp_path):
    data = setup[0]
    real = OLATDataset(data)
    train_from_preset(data, tmp_path / "base", regime="views=2,lights=1", overrides=TRAIN, show_progress=False)
    scene = load_scene(tmp_path / "base")[0]
    camera, light = real.cameras[3], real.lights[2]
    with torch.no_grad():
        render = scene.render(camera.w2c[None], camera.K[None], camera.width, camera.height, light.position[None],
                              light.intensity[None])
    radiance, alpha = render.radiance[0], render.gbuffer.alpha[0]
    same = write_png(tmp_path / "same.png", to_srgb8(radiance, alpha))
    black = write_png(tmp_path / "black.png", to_srgb8(torch.zeros_like(radiance), alpha))
    errors = render_errors(scene, real, [GeneratedImage(3, 2, same), GeneratedImage(3, 2, black)])
    srgb = linear_to_srgb(radiance.clamp_min(0.0))
    assert errors[0] < 2.0 / 255.0  # 8-bit quantisation only
    assert errors[1] == pytest.approx(float((srgb * alpha).sum() / (3 * alpha.sum())), abs=2.0 / 255.0)
    # an image made at 8x8 (a diffusion model's resolution) against the render area-downsampled to 8x8
    small = write_png(tmp_path / "small.png", to_srgb8(resize_area(radiance, 8, 8), resize_area(alpha, 8, 8)))
    assert render_errors(scene, real, [GeneratedImage(3, 2, small)])[0] < 2.0 / 255.0
    with pytest.raises(ValueError, match=r"image is 32x32, the lattice's view 3 is 16x16 \(it may be smaller"):
        large = write_png(tmp_path / "large.png", to_srgb8(*(x.repeat_interleave(2, 0).repeat_interleave(2, 1)
                                                              for x in (radiance, alpha))))
        render_errors(scene, real, [GeneratedImage(3, 2, large)])
    with pytest.raises(ValueError, match="same.png: view 99 / light 2 outside the lattice's 6 views x 3 lights"):
        render_errors(scene, real, [GeneratedImage(99, 2, same)])


def test_image_source_weights_per_image(setup):
    real = OLATDataset(setup[0])
    factors = tuple(i / len(real) for i in range(len(real)))
    source = ImageSource(real, 0.5, factors)
    assert source.weight_of(4) == pytest.approx(0.5 * 4 / len(real)) and ImageSource(real, 0.5).weight_of(4) == 0.5
    with pytest.raises(ValueError, match=f"2 factors for the {len(real)} images"):
        ImageSource(real, 0.5, (1.0, 1.0))
    with pytest.raises(ValueError, match="finite and >= 0"):
        ImageSource(real, 0.5, (-1.0,) * len(real))


def test_spread_subset():
    dirs = torch.nn.functional.normalize(torch.randn(10, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    assert spread_subset([1, 4, 7], dirs, 0, 0) == [1, 4, 7]
    picked = spread_subset(list(range(10)), dirs, 3, 0)
    assert len(picked) == 3 and picked == spread_subset(list(range(10)), dirs, 3, 0)


def test_pipeline_end_to_end_and_resume(setup, tmp_path, capsys):
    data, nvs, relight, cache = setup
    cfg = PipelineConfig(nvs_views=2, relight_lights=1, nvs_model=str(nvs), relight_model=str(relight),
                         nvs_steps=2, relight_steps=2, min_silhouette_iou=0.0, min_mask_fraction=0.0, cache_dir=str(cache),
                         agreement_power=1.0)
    result = run_pipeline(data, tmp_path, regime="views=2,lights=1", overrides=TRAIN, config=cfg)
    progress = capsys.readouterr().err  # each diffusion stage shows its progress (on a terminal, or in a log)
    assert re.search(r"nvs: 100%\|[^|]*\| 2/2 ", progress) and re.search(r"relight: 100%\|[^|]*\| 4/4 ", progress)
    manifest = json.loads((tmp_path / "pipeline.json").read_text())
    assert list(manifest["stages"]) == ["prelim", "nvs", "relight", "final", "eval"]
    assert set(manifest["inputs"]["model_hashes"]) == {"nvs", "relight"}
    # 2 novel views under the 1 real light, then 4 views (2 real + 2 generated) relit to 1 missing light
    assert manifest["stages"]["nvs"]["targets"] == 2
    assert manifest["stages"]["relight"]["images"] == 4
    assert result["synthetic_images"] == 6 and result["real_images"] == 2 and result["real_share"] == 0.25
    assert manifest["stages"]["final"]["real_share"] == 0.25
    agreement = manifest["stages"]["final"]["agreement"]
    # the 3 of 6 generated images above the median error lose weight
    assert 0.0 < agreement["min_factor"] < agreement["mean_factor"] < 1.0 and agreement["down_weighted"] == 3
    assert {"psnr", "ssim", "mask_iou"} <= set(result)
    synthetic = OLATDataset(tmp_path / "synthetic", "train")
    assert len(synthetic) == 6 and synthetic.num_views == 6
    # the finished stages are reused, also where the diffusion models would now run on another device and cache
    moved = replace(cfg, device="cuda", cache_dir=str(tmp_path / "other_cache"))
    again = run_pipeline(data, tmp_path, regime="views=2,lights=1", overrides=TRAIN, config=moved, show_progress=False)
    assert again["psnr"] == result["psnr"]
    with pytest.raises(ValueError, match=r"other inputs \(regime: 'views=2,lights=1' -> 'views=3,lights=1'\);"):
        run_pipeline(data, tmp_path, regime="views=3,lights=1", overrides=TRAIN, config=cfg, show_progress=False)


def test_prelim_reuses_a_finished_reconstruction(setup, tmp_path):
    data, _, relight, cache = setup
    base = tmp_path / "base"
    train_from_preset(data, base, regime="views=2,lights=1", overrides=TRAIN, show_progress=False)
    cfg = PipelineConfig(augment=("relight",), relight_lights=1, relight_model=str(relight), relight_steps=1,
                         relight_samples=1, min_silhouette_iou=0.0, min_mask_fraction=0.0, cache_dir=str(cache),
                         prelim_run=str(base))
    result = run_pipeline(data, tmp_path / "run", regime="views=2,lights=1", overrides=TRAIN, config=cfg,
                          show_progress=False)
    manifest = json.loads((tmp_path / "run" / "pipeline.json").read_text())
    assert manifest["stages"]["prelim"]["reused"] == str(base)
    assert not (tmp_path / "run" / "prelim").exists()
    assert result["real_images"] == 2 and result["synthetic_images"] == 2 and result["real_share"] == 0.5
    assert result["real_draw_share"] == 0.5 and "agreement" not in result  # power 0: no render, every image at alpha
    shared = run_pipeline(data, tmp_path / "shared", regime="views=2,lights=1", overrides=TRAIN,
                          config=replace(cfg, min_real_share=0.7), show_progress=False)
    assert shared["real_share"] == 0.5 and shared["real_draw_share"] == 0.75  # the real images drawn 3x as often
    with pytest.raises(ValueError, match="'min_real_share' must be in"):
        run_pipeline(data, tmp_path / "bad", config=replace(cfg, min_real_share=1.0))
    with pytest.raises(ValueError, match="'generated_as_real' must be a finite number > 0, got 0"):
        run_pipeline(data, tmp_path / "bad", config=replace(cfg, generated_as_real=0.0))
    with pytest.raises(ValueError, match="'agreement_power' must be a finite number >= 0"):
        run_pipeline(data, tmp_path / "bad", config=replace(cfg, agreement_power=float("nan")))
    with pytest.raises(ValueError, match=r"base/regime.json lists other images"):
        run_pipeline(data, tmp_path / "other", regime="views=3,lights=1", overrides=TRAIN, config=cfg,
                     show_progress=False)
    missing = PipelineConfig(augment=("relight",), relight_model=str(relight), prelim_run=str(tmp_path / "none"))
    with pytest.raises(ValueError, match=r"none/model.safetensors is missing"):
        run_pipeline(data, tmp_path / "third", regime="views=2,lights=1", overrides=TRAIN, config=missing,
                     show_progress=False)


def test_a_preliminary_run_is_reused_after_its_capture_moved_but_not_with_other_images(setup, tmp_path):
    data, _, relight, cache = setup
    base = tmp_path / "base"
    train_from_preset(data, base, regime="views=2,lights=1", overrides=TRAIN, show_progress=False)
    moved = shutil.copytree(data, tmp_path / "moved")
    cfg = PipelineConfig(augment=("relight",), relight_lights=1, relight_model=str(relight), relight_steps=1,
                         relight_samples=1, min_silhouette_iou=0.0, min_mask_fraction=0.0, cache_dir=str(cache),
                         prelim_run=str(base))
    result = run_pipeline(moved, tmp_path / "run", regime="views=2,lights=1", overrides=TRAIN, config=cfg,
                          show_progress=False)
    assert json.loads((tmp_path / "run" / "pipeline.json").read_text())["stages"]["prelim"]["reused"] == str(base)
    assert result["real_images"] == 2
    used = OLATDataset(moved).observations[json.loads((base / "regime.json").read_text())["observations"][0]]
    image = iio.imread(used.image_path)
    image[0, 0, 0] ^= 1  # one bit of one of the run's images
    iio.imwrite(used.image_path, image)
    with pytest.raises(ValueError, match=r"base/data.json records data .*: the images differ"):
        run_pipeline(moved, tmp_path / "other", regime="views=2,lights=1", overrides=TRAIN, config=cfg,
                     show_progress=False)
    record = json.loads((base / "data.json").read_text())
    (base / "data.json").write_text(json.dumps({k: v for k, v in record.items() if k != "content_sha256"}))
    with pytest.raises(ValueError, match=r"records no content digest"):  # a run trained before the digest
        run_pipeline(moved, tmp_path / "older", regime="views=2,lights=1", overrides=TRAIN, config=cfg,
                     show_progress=False)
    assert run_pipeline(data, tmp_path / "in_place", regime="views=2,lights=1", overrides=TRAIN, config=cfg,
                        show_progress=False)["real_images"] == 2  # at its recorded path it needs no digest


def test_a_run_with_other_inputs_is_moved_aside_not_deleted(tmp_path):
    out = tmp_path / "diamond"
    (out / "prelim").mkdir(parents=True)
    record = json.dumps({"inputs": {"model": "a"}, "stages": {"prelim": {}}})
    (out / "pipeline.json").write_text(record)
    assert move_aside_if_changed(out, {"model": "a"}) is None and (out / "prelim").is_dir()
    moved = move_aside_if_changed(out, {"model": "b"})
    assert moved == tmp_path / f"diamond.{sha256_json({'model': 'a'})[:8]}"
    assert (moved / "prelim").is_dir() and not out.exists()
    # A second stale run with the same inputs does not replace the first one.
    out.mkdir()
    (out / "pipeline.json").write_text(record)
    assert move_aside_if_changed(out, {"model": "b"}) == moved.with_name(moved.name + "-2")
    assert move_aside_if_changed(tmp_path / "never_run", {"model": "a"}) is None
    out.mkdir()
    (out / "pipeline.json").write_text('{"inputs": ')
    with pytest.raises(ValueError, match=r"diamond/pipeline.json is not valid JSON"):
        move_aside_if_changed(out, {"model": "b"})


def test_a_run_resumes_on_another_device_or_cache_but_not_with_other_inputs(tmp_path):
    path = tmp_path / "pipeline.json"
    inputs = {"regime": "views=3", "pipeline": {"rounds": 1, "device": "cpu", "cache_dir": None}}
    PipelineManifest(path, inputs).record(StageRecord("prelim", 1.0, {"real_images": 3}))
    elsewhere = {"regime": "views=3", "pipeline": {"rounds": 1, "device": "cuda", "cache_dir": "/other/cache"}}
    resumed = PipelineManifest(path, elsewhere)
    assert resumed.done("prelim") == {"seconds": 1.0, "real_images": 3}
    resumed.record(StageRecord("nvs", 2.0))
    assert json.loads(path.read_text())["inputs"] == elsewhere  # recorded as the latest run had them
    assert move_aside_if_changed(tmp_path, elsewhere) is None and path.is_file()
    other = {**elsewhere, "pipeline": {**elsewhere["pipeline"], "rounds": 2}}
    with pytest.raises(ValueError, match=r"other inputs \(pipeline\.rounds: 1 -> 2\);"):
        PipelineManifest(path, other)


def test_a_downscaled_run_generates_its_images_at_the_reconstructions_size(setup, tmp_path):
    data = tmp_path / "capture"
    make_capture(data, views=6, lights=3, size=32)
    _, nvs, relight, _ = setup
    cfg = PipelineConfig(nvs_views=2, relight_lights=1, nvs_model=str(nvs), relight_model=str(relight),
                         relight_samples=1, min_silhouette_iou=0.0, min_mask_fraction=0.0, cache_dir=str(tmp_path / "c"))
    result = run_pipeline(data, tmp_path / "run", regime="views=2,lights=1", overrides={**TRAIN, "downscale": 2.0},
                          config=cfg, show_progress=False)
    assert result["synthetic_images"] == 6 and result["dropped"] == {}
    synthetic = OLATDataset(tmp_path / "run" / "synthetic", "train")
    assert (synthetic.width, synthetic.height) == (16, 16) and len(synthetic) == 6
    generated = [*(tmp_path / "run" / "nvs").glob("*/images/*.png"), *(tmp_path / "run" / "relight" / "out").glob(
        "images/*.png")]
    assert len(generated) == 6 and {iio.imread(path).shape[:2] for path in generated} == {(16, 16)}


def test_changed_inputs_name_each_differing_key():
    recorded = {"regime": "views=3", "pipeline": {"rounds": 1, "nvs_steps": 25}, "seed": 0}
    given = {"regime": "views=3", "pipeline": {"rounds": 2, "nvs_steps": 25, "prelim_preset": None}, "seed": 0}
    assert changed_inputs(recorded, given) == ["pipeline.prelim_preset: missing -> None", "pipeline.rounds: 1 -> 2"]
    assert changed_inputs(recorded, recorded) == []
    assert changed_inputs(None, {"seed": 0}) == ["inputs: None -> {'seed': 0}"]
    many = {"overrides": {f"k{i}": i for i in range(9)}}
    assert listed_changes(many, {"overrides": {}}, most=2) == (
        "overrides.k0: 0 -> missing; overrides.k1: 1 -> missing; and 7 more")
    assert listed_changes(recorded, given) == "pipeline.prelim_preset: missing -> None; pipeline.rounds: 1 -> 2"


def test_a_pipeline_setting_added_since_a_run_was_recorded_reads_as_its_default(tmp_path):
    cfg = PipelineConfig()
    given = {"regime": "all", "pipeline": asdict(cfg) | {"augment": list(cfg.augment)}}
    recorded = {"regime": "all", "pipeline": {k: v for k, v in given["pipeline"].items() if k != "repair_model"}}
    assert compared_inputs(recorded) == compared_inputs(given)  # the run made before repair_model is not redone
    changed = {"regime": "all", "pipeline": {**given["pipeline"], "repair_model": "elsewhere"}}
    assert changed_inputs(compared_inputs(recorded), compared_inputs(changed)) == [
        "pipeline.repair_model: None -> 'elsewhere'"]


def test_relighting_targets_the_lights_each_view_lacks(setup, tmp_path):
    # All views under one light each, the lights spread over the views: every lattice light is used by some view,
    # yet each view still lacks the others and is relit to them.
    data, _, relight, cache = setup
    cfg = PipelineConfig(augment=("relight",), relight_lights=0, relight_model=str(relight), relight_steps=1,
                         relight_samples=1, min_silhouette_iou=0.0, min_mask_fraction=0.0, cache_dir=str(cache))
    run_pipeline(data, tmp_path, regime="all-views-1-light", overrides=TRAIN, config=cfg, show_progress=False)
    real = {(o.view, o.light) for o in OLATDataset(tmp_path / "relight", "sources").observations}
    relit = json.loads((tmp_path / "relight" / "out" / "manifest.json").read_text())
    assert len({light for _, light in real}) > 1
    assert sorted((e["view"], e["light"]) for e in relit) == sorted(
        (view, light) for view, _ in real for light in range(3) if (view, light) not in real
    )


def test_sanity_checks_drop_bad_generations(setup, tmp_path):
    data, nvs, _, cache = setup
    cfg = PipelineConfig(augment=("nvs",), nvs_views=2, nvs_model=str(nvs), nvs_steps=2,
                         min_silhouette_iou=1.01, cache_dir=str(cache))
    # both novel views dropped: the run stops before a final reconstruction that would skip the method
    with pytest.raises(ValueError, match=r"--augment nvs generated no image \(every generated image was dropped "
                                         r"\(silhouette: 2\).*lower min_silhouette_iou"):
        run_pipeline(data, tmp_path, regime="views=2,lights=1", overrides=TRAIN, config=cfg, show_progress=False)
    assert json.loads((tmp_path / "pipeline.json").read_text())["stages"]["nvs"]["targets"] == 2
    assert not (tmp_path / "final").exists()
    with pytest.raises(ValueError, match="unknown stage"):
        run_pipeline(data, tmp_path / "x", config=PipelineConfig(augment=("nvs", "super-resolution")))


def test_rounds_reuse_each_final_reconstruction_as_the_next_preliminary_one(setup, tmp_path):
    data, _, relight, cache = setup
    cfg = PipelineConfig(augment=("relight",), relight_lights=1, relight_model=str(relight), relight_steps=1,
                         relight_samples=1, min_silhouette_iou=0.0, min_mask_fraction=0.0, cache_dir=str(cache),
                         rounds=2)
    result = run_pipeline(data, tmp_path, regime="views=2,lights=1", overrides=TRAIN, config=cfg, show_progress=False)
    first = json.loads((tmp_path / "round1" / "pipeline.json").read_text())
    last = json.loads((tmp_path / "pipeline.json").read_text())
    assert first["inputs"]["pipeline"]["prelim_run"] is None and (tmp_path / "round1" / "prelim").is_dir()
    assert last["inputs"]["pipeline"]["prelim_run"] == str(tmp_path / "round1" / "final")
    assert last["stages"]["prelim"]["reused"] == str(tmp_path / "round1" / "final")
    assert last["inputs"]["prelim_model_hash"] == sha256_file(tmp_path / "round1" / "final" / "model.safetensors")
    assert result["round_psnr"] == [first["stages"]["eval"]["psnr"], result["psnr"]]
    again = run_pipeline(data, tmp_path, regime="views=2,lights=1", overrides=TRAIN, config=cfg, show_progress=False)
    assert again == result  # both rounds resume from their records
    for bad, message in ((replace(cfg, rounds=0), "'rounds' must be an integer >= 1, got 0"),
                         (replace(cfg, augment=()), "'rounds' > 1 needs a diffusion stage"),
                         (replace(cfg, prelim_iterations=0),
                          r"'prelim_iterations' \(--prelim-iterations\) must be a positive number of training steps"),
                         (replace(cfg, nvs_views=-1), r"'nvs_views' \(--nvs-views\) must be an integer >= 0"),
                         (replace(cfg, relight_samples=0), "'relight_samples' .* must be an integer >= 1, got 0")):
        with pytest.raises(ValueError, match=message):
            run_pipeline(data, tmp_path / "bad", config=bad)


def test_parse_augment_and_missing_models(setup, tmp_path):
    from diamond_sss.pipeline.run import parse_augment

    assert parse_augment("none") == () and parse_augment("nvs, relight") == ("nvs", "relight")
    with pytest.raises(ValueError, match="unknown stage"):
        parse_augment("nvs,upscale")
    cfg = PipelineConfig(augment=("relight",), relight_model=str(tmp_path / "missing"))
    with pytest.raises(FileNotFoundError, match="no relight model in .*missing: pass --relight-model"):
        run_pipeline(setup[0], tmp_path / "run", overrides=TRAIN, config=cfg, show_progress=False)


def test_auto_augment_follows_the_shipped_model_folders(tmp_path, monkeypatch):
    from diamond_sss.diffusion.nvs import pipeline as nvs_pipeline
    from diamond_sss.diffusion.relight import inference as relight_inference
    from diamond_sss.diffusion.repair import pipeline as repair_pipeline
    from diamond_sss.pipeline.run import parse_augment

    assert parse_augment("auto") == ("repair",)  # the repair model ships with the package
    repair_dir = tmp_path / "repair"
    monkeypatch.setattr(repair_pipeline, "default_model_dir", lambda: repair_dir)
    assert parse_augment("auto") == ("nvs", "relight")  # without it, the paper's stages whose models ship
    repair_dir.mkdir()
    (repair_dir / "config.json").write_text("{}")
    assert parse_augment("auto") == ("nvs", "relight")  # a folder without weights is no model
    nvs_dir, relight_dir = tmp_path / "nvs", tmp_path / "relight"
    monkeypatch.setattr(nvs_pipeline, "default_model_dir", lambda: nvs_dir)
    monkeypatch.setattr(relight_inference, "shipped_model_path", lambda: relight_dir)
    assert parse_augment("auto") == ()
    relight_dir.mkdir()
    (relight_dir / "config.json").write_text("{}")
    assert parse_augment("auto") == ("relight",)
    nvs_dir.mkdir()
    assert parse_augment("auto") == ("relight",)  # a folder without config.json is no model
    (nvs_dir / "config.json").write_text("{}")
    assert parse_augment("auto") == ("nvs", "relight")


def test_the_novel_views_warp_with_the_geometry_given_or_else_the_preliminary_reconstruction(setup, tmp_path):
    from diamond_sss.diffusion.geometry import StoredMapsGeometry
    from diamond_sss.diffusion.geometry.sources import RenderedGeometry
    from diamond_sss.pipeline.run import checked_config, nvs_geometry

    prelim = tmp_path / "prelim"
    train_from_preset(setup[0], prelim, regime="views=2,lights=1", overrides=TRAIN, show_progress=False)
    default = nvs_geometry(PipelineConfig(), prelim)
    assert isinstance(default, RenderedGeometry) and default.run == prelim
    assert isinstance(nvs_geometry(PipelineConfig(nvs_geometry="maps"), prelim), StoredMapsGeometry)
    assert nvs_geometry(PipelineConfig(nvs_geometry=str(prelim)), tmp_path / "unused").run == prelim
    with pytest.raises(ValueError, match="pipeline config 'nvs_geometry': geometry source .*missing"):
        checked_config(PipelineConfig(nvs_geometry=str(tmp_path / "missing")))


def test_prelim_iterations_scale_the_final_reconstructions_schedule(setup, tmp_path):
    import diamond_sss.pipeline.run as pipeline_run
    from diamond_sss.training.config import short_schedule
    from diamond_sss.training.overrides import make_config

    data, _, relight, _ = setup
    cfg = PipelineConfig(augment=("relight",), relight_model=str(relight), prelim_iterations=400)
    ctx, _ = pipeline_run.prepare_run(data, tmp_path, split="train", regime="views=2,lights=1", preset="diamond",
                                      overrides={**short_schedule(1000), "device": "cpu"}, seed=3, cfg=cfg,
                                      show_progress=False)
    prelim = ctx.prelim_cfg
    # every step-valued key scaled by 400 / 1000, also those short_schedule leaves at the preset's (image logs)
    assert prelim == make_config("diamond", overrides={**short_schedule(400), "image_log_every": 200,
                                                       "device": "cpu", "seed": 3})
    assert (prelim.schedule.iterations, prelim.lr.decay_step, prelim.densify.refine_stop_iter) == (400, 280, 340)
    assert ctx.train_cfg.schedule.iterations == 1000


def test_the_preliminary_reconstruction_takes_its_own_preset_and_overrides(setup, tmp_path, monkeypatch):
    import diamond_sss.pipeline.run as pipeline_run
    from diamond_sss.training.config import short_schedule
    from diamond_sss.training.overrides import make_config

    data, _, relight, _ = setup
    seen = {}
    monkeypatch.setattr(pipeline_run, "train_run", lambda data, out, config, **kwargs: seen.update(config=config) or
                        type("Result", (), {"steps": 0})())
    final = {**short_schedule(1000, pipeline_final=True), "device": "cpu"}
    prelim = {**short_schedule(1000), "device": "cpu"}
    cfg = PipelineConfig(augment=("relight",), relight_model=str(relight), prelim_preset="sss3dgs",
                         prelim_iterations=500)
    ctx, inputs = pipeline_run.prepare_run(data, tmp_path, split="train", regime="views=2,lights=1", preset="diamond",
                                           overrides=final, prelim_overrides=prelim, seed=3, cfg=cfg,
                                           show_progress=False)
    pipeline_run.prelim_stage(ctx)
    assert inputs["preset"] == "diamond" and inputs["prelim_overrides"] == {**prelim, "seed": 3}
    trained = seen["config"]  # the configuration prepare_run resolved, handed down as it is
    assert trained is ctx.prelim_cfg and trained == make_config(
        "sss3dgs", overrides={**short_schedule(500), "image_log_every": 250, "device": "cpu", "seed": 3})
    assert trained.losses.photometric_error == "l1" and ctx.train_cfg.losses.photometric_error == "rmse"
    with pytest.raises(ValueError, match="unknown preset"):
        pipeline_run.prepare_run(data, tmp_path / "bad", split="train", regime="views=2,lights=1", preset="diamond",
                                 overrides=final, prelim_overrides=None, seed=3,
                                 cfg=PipelineConfig(augment=("relight",), relight_model=str(relight),
                                                    prelim_preset="sss4dgs"), show_progress=False)
    assert not (tmp_path / "bad").exists()  # refused before the run's folder is made


def test_a_pipeline_run_resolves_each_reconstructions_configuration_once(setup, tmp_path, monkeypatch):
    """The preliminary and the final configurations are made once each, in prepare_run, and handed down to the
    trainings (before issue 61: 8 calls, 5 of them resolving the same two recipes again); the generated images
    weigh the pipeline's synthetic_weight."""
    import sys

    import diamond_sss.pipeline.run as pipeline_run
    from diamond_sss.training import overrides

    data, _, relight, cache = setup
    original, calls, trained = overrides.make_config, [], {}

    def counted(*args, **kwargs):
        calls.append(args[:1] or kwargs.get("preset"))
        return original(*args, **kwargs)

    def recorded(data, out, config, **kwargs):
        trained[out.name] = (config, [source.weight for source in kwargs.get("extra_sources", ())])
        return train_run(data, out, config, **kwargs)

    for module in [module for name, module in sys.modules.items() if name.startswith("diamond_sss")]:
        if getattr(module, "make_config", None) is original:
            monkeypatch.setattr(module, "make_config", counted)
    train_run = pipeline_run.train_run
    monkeypatch.setattr(pipeline_run, "train_run", recorded)
    cfg = PipelineConfig(augment=("relight",), relight_lights=1, relight_model=str(relight), relight_steps=1,
                         relight_samples=1, min_silhouette_iou=0.0, min_mask_fraction=0.0, cache_dir=str(cache),
                         prelim_iterations=3, synthetic_weight=0.25)
    run_pipeline(data, tmp_path, regime="views=2,lights=1", overrides=TRAIN, config=cfg, show_progress=False)
    assert len(calls) == 2, calls
    assert trained["prelim"][0].schedule.iterations == 3 and trained["final"][0].schedule.iterations == 2
    assert trained["final"][1] == [0.25]  # the one generated source (power 0: no extra real copies here)
    inputs = json.loads((tmp_path / "pipeline.json").read_text())["inputs"]
    assert inputs["pipeline"]["synthetic_weight"] == 0.25 and inputs["overrides"] == {**TRAIN, "seed": 0}
    calls.clear()
    again = run_pipeline(data, tmp_path, regime="views=2,lights=1", overrides=TRAIN, config=cfg, show_progress=False)
    assert len(calls) == 2 and "psnr" in again  # resumed: every stage's record reused, the inputs the same


def test_synthetic_weight_is_a_pipeline_setting_and_earlier_runs_still_load(setup, tmp_path, capsys, monkeypatch):
    """synthetic_weight (issue 61: a reconstruction key before, read only by the pipeline) is the pipeline's
    --synthetic-weight: given as a config key it is refused naming that flag, before anything is written; a run
    folder's config.json and a pipeline.json recorded with it still load and resume."""
    import diamond_sss.pipeline.run as pipeline_run
    from diamond_sss.cli.main import main
    from diamond_sss.pipeline.run import checked_config, compared_inputs
    from diamond_sss.training.overrides import load_run_config, make_config

    assert PipelineConfig().synthetic_weight == 0.5
    for key in ("synthetic_weight", "losses.synthetic_weight"):
        with pytest.raises(ValueError, match=f"config key '{key}' is a setting of the pipeline.*--synthetic-weight"):
            make_config(sets=[f"{key}=1"])
    path = tmp_path / "best.json"
    path.write_text(json.dumps({"losses": {"synthetic_weight": 1.0}}))
    with pytest.raises(ValueError, match="best.json: config key 'losses.synthetic_weight' is a setting of the"):
        make_config(config_file=path)
    with pytest.raises(ValueError, match=r"'synthetic_weight' \(--synthetic-weight\) must be a finite number >= 0"):
        checked_config(PipelineConfig(synthetic_weight=-1.0))
    for command in ("train", "run"):
        out = tmp_path / command
        with pytest.raises(SystemExit):
            main([command, "--data", str(setup[0]), "--out", str(out), "--quiet", "--set", "synthetic_weight=1"])
        assert "give it to `diamond-sss run` as --synthetic-weight" in capsys.readouterr().err
        assert not out.exists()
    seen = {}
    monkeypatch.setattr(pipeline_run, "run_pipeline", lambda data, out, **kwargs: seen.update(kwargs) or {})
    main(["run", "--data", str(setup[0]), "--out", str(tmp_path / "run"), "--quiet", "--synthetic-weight", "0.25"])
    assert seen["config"].synthetic_weight == 0.25
    # an earlier run's config.json, nested or flat, records the key: it loads without it
    run = tmp_path / "earlier"
    run.mkdir()
    nested = make_config("sss3dgs").to_dict()
    nested["losses"]["synthetic_weight"] = 0.5
    (run / "config.json").write_text(json.dumps(nested))
    assert load_run_config(run) == make_config("sss3dgs")
    (run / "config.json").write_text(json.dumps({**make_config("sss3dgs").flat(), "synthetic_weight": 0.5}))
    assert load_run_config(run) == make_config("sss3dgs")
    # an earlier pipeline.json: the final reconstruction's value (else the default) reads as the pipeline's setting
    now = {"overrides": {"seed": 0}, "prelim_overrides": {"seed": 0}, "pipeline": {"synthetic_weight": 1.0}}
    before = {"overrides": {"seed": 0, "synthetic_weight": 1.0}, "prelim_overrides": {"seed": 0,
                                                                                      "synthetic_weight": 1.0},
              "pipeline": {}}
    assert compared_inputs(before) == compared_inputs(now)
    default = {**now, "pipeline": {"synthetic_weight": 0.5}}
    assert compared_inputs({**before, "overrides": {"seed": 0}, "prelim_overrides": {"seed": 0}}) == compared_inputs(
        default) != compared_inputs(now)
