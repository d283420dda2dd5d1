"""Novel-view inference command: outputs, manifest, cache, determinism and clear errors for bad input."""

from __future__ import annotations

import dataclasses
import json

import imageio.v3 as iio
import pytest
import torch
from capture_edits import copy_with_mask_files
from tiny_models import TINY_NVS

from diamond_sss.cli.main import main
from diamond_sss.cli.nvs_commands import nvs
from diamond_sss.data.analytic import make_capture
from diamond_sss.data.conventions import scale_intrinsics
from diamond_sss.data.images import reframe
from diamond_sss.diffusion.common.manifest import read_image_manifest
from diamond_sss.diffusion.nvs import pipeline
from diamond_sss.diffusion.nvs.data import load_rgba_views
from diamond_sss.diffusion.nvs.model import NVSConfig, NVSModel
from diamond_sss.pipeline.capture import check_on_lattice

TINY = {**TINY_NVS, "warp_hint": False}
"""The base model (no warp hint); the hint is tested in test_nvs_warp.py."""


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    data = tmp_path_factory.mktemp("capture")
    make_capture(data, views=5, lights=2, size=24)
    torch.manual_seed(0)
    model_dir = NVSModel(NVSConfig(**TINY)).save(tmp_path_factory.mktemp("model"))
    return data, model_dir, tmp_path_factory.mktemp("cache")


def run(setup, out, targets=(1, 3), **kwargs):
    """The library with typed targets; a string goes through the command line's parser first."""
    data, model_dir, cache = setup
    if isinstance(targets, str):
        targets = pipeline.parse_targets(targets, pipeline.OLATDataset(data))
    return pipeline.generate_novel_views(
        data,
        out,
        kwargs.pop("view", 0),
        kwargs.pop("light", 1),
        targets,
        model_dir=model_dir,
        steps=2,
        cache_dir=kwargs.pop("cache_dir", cache),
        **kwargs,
    )


def test_outputs_manifest_and_cache(setup, tmp_path, monkeypatch):
    manifest_path = run(setup, tmp_path / "a")
    manifest = json.loads(manifest_path.read_text())
    assert manifest == [
        {"view": 1, "light": 1, "image": "images/view_001.png", "mask": "masks/view_001.png"},
        {"view": 3, "light": 1, "image": "images/view_003.png", "mask": "masks/view_003.png"},
    ]
    image = iio.imread(tmp_path / "a" / "images" / "view_001.png")
    mask = iio.imread(tmp_path / "a" / "masks" / "view_001.png")
    assert image.shape == (16, 16, 4) and mask.shape == (16, 16)  # the model's size, not the 24 px capture's
    assert (image[..., 3] == mask).all()

    def no_model(*args, **kwargs):
        raise AssertionError("the cache should have answered")

    monkeypatch.setattr(pipeline.NVSModel, "load", no_model)
    run(setup, tmp_path / "b")
    image = ("images", "view_003.png")
    assert (tmp_path.joinpath("a", *image)).read_bytes() == (tmp_path.joinpath("b", *image)).read_bytes()
    monkeypatch.undo()
    # another seed is another cache entry and other images
    run(setup, tmp_path / "c", seed=1)
    assert (tmp_path.joinpath("a", *image)).read_bytes() != (tmp_path.joinpath("c", *image)).read_bytes()
    # a model loaded once by the caller (the pipeline's stage) makes the same images as one loaded per call
    loaded = pipeline.NVSModel.load(setup[1])
    monkeypatch.setattr(pipeline.NVSModel, "load", no_model)
    run(setup, tmp_path / "d", cache_dir=tmp_path / "fresh_cache", model=loaded)
    assert (tmp_path.joinpath("a", *image)).read_bytes() == (tmp_path.joinpath("d", *image)).read_bytes()


def test_json_poses_through_the_command(setup, tmp_path):
    data, model_dir, cache = setup
    frames = json.loads((data / "transforms_train.json").read_text())["frames"]
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps([frames[2]["transform_matrix"], frames[4]["transform_matrix"]]))
    nvs(
        data, view=0, light=0, targets=str(poses), out=tmp_path / "out", model=model_dir, steps=1, cache=cache
    )
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert [m["image"] for m in manifest] == ["images/pose_000.png", "images/pose_001.png"]
    assert all((tmp_path / "out" / m["mask"]).is_file() for m in manifest)
    # free poses are no lattice views: the manifest says so, and a capture on the lattice refuses them
    assert [m["view"] for m in manifest] == [None, None]
    items = read_image_manifest(tmp_path / "out" / "manifest.json")
    assert [item.view for item in items] == [None, None]
    with pytest.raises(ValueError, match=r"pose_000\.png: a novel view at a camera given by its pose"):
        check_on_lattice(items, pipeline.OLATDataset(data))
    # the same cameras given as lattice indices give the same targets
    same = pipeline.parse_targets("2,4", pipeline.OLATDataset(data))
    parsed = pipeline.parse_targets(str(poses), pipeline.OLATDataset(data))
    torch.testing.assert_close(parsed.w2c, same.w2c, atol=1e-5, rtol=0)


@pytest.mark.parametrize(
    ("targets", "message"),
    [
        ("1,9", r"unknown view index \[9\]"),
        ("one,two", "view indices"),
        ("[[1, 0], [0, 1]]", "4x4"),
        ('{"frames": [{"matrix": 1}]}', "transform_matrix"),
        ("{not json", "malformed pose JSON"),
    ],
)
def test_bad_targets_give_clear_errors(setup, tmp_path, targets, message):
    with pytest.raises(ValueError, match=message):
        run(setup, tmp_path, targets=targets)


def test_bad_reference_and_pose_file_give_clear_errors(setup, tmp_path):
    with pytest.raises(ValueError, match="unknown view index 7"):
        run(setup, tmp_path, view=7)
    with pytest.raises(ValueError, match="unknown light index 5"):
        run(setup, tmp_path, light=5)
    bad = tmp_path / "bad.json"
    bad.write_text("[[1, 0, 0, 0], [0, 1, 0, 0]")
    with pytest.raises(ValueError, match="malformed pose JSON in .*bad.json"):
        run(setup, tmp_path, targets=str(bad))
    with pytest.raises(ValueError, match="not found"):
        run(setup, tmp_path, targets=str(tmp_path / "missing.json"))


def test_the_library_takes_typed_targets_not_command_line_text(setup, tmp_path):
    data, _, _ = setup
    cameras = pipeline.TargetCameras.from_views(pipeline.OLATDataset(data), [3, 1])
    assert cameras.views == [3, 1] and cameras.names == ["view_003", "view_001"] and cameras.size == 24
    assert json.loads(run(setup, tmp_path / "a", targets=cameras).read_text())[0]["view"] == 3
    with pytest.raises(TypeError, match="parse_targets"):
        pipeline.generate_novel_views(data, tmp_path / "b", 0, 1, "1,3", model_dir=setup[1], cache_dir=setup[2])
    with pytest.raises(ValueError, match=r"unknown view index \[True\]"):
        run(setup, tmp_path / "c", targets=[True])


def test_the_reference_mask_file_is_part_of_the_cache_key(setup, tmp_path, monkeypatch):
    data = copy_with_mask_files(setup[0], tmp_path / "data")
    cache = tmp_path / "cache"
    first = run((data, setup[1], cache), tmp_path / "a")
    loads = []
    load = pipeline.NVSModel.load
    monkeypatch.setattr(pipeline.NVSModel, "load", lambda *a, **k: loads.append(1) or load(*a, **k))
    run((data, setup[1], cache), tmp_path / "b")
    assert not loads  # the same inputs: served from the cache
    mask = pipeline.OLATDataset(data).observations[1].mask_path  # the reference's: view 0, light 1
    eroded = iio.imread(mask)
    eroded[: eroded.shape[0] // 2] = 0
    iio.imwrite(mask, eroded)
    run((data, setup[1], cache), tmp_path / "c")
    assert loads == [1]  # another reference mask: generated again, into another entry
    assert len([entry for folder in cache.iterdir() for entry in folder.iterdir()]) == 2
    assert json.loads(first.read_text()) == json.loads((tmp_path / "c" / "manifest.json").read_text())


def test_finetune_nvs_model_options_given_at_their_defaults_still_win_over_the_init_models(tmp_path, monkeypatch):
    import diamond_sss.diffusion.nvs.train as nvs_train

    saved = NVSConfig(**{**TINY_NVS, "hint_residual": True, "prediction_type": "v_prediction"})
    NVSModel(saved).save(tmp_path / "init")
    seen = {}
    monkeypatch.setattr(nvs_train, "finetune", lambda data, out, config, **_: seen.update(config=config) or out)
    base = ["finetune-nvs", "--out", str(tmp_path / "run"), "--data", str(tmp_path)]
    main([*base, "--init-from", str(tmp_path / "init")])
    assert seen["config"].model == saved
    main([*base, "--init-from", str(tmp_path / "init"), "--no-hint-residual", "--prediction-type", "epsilon",
          "--image-size", "32"])
    assert seen["config"].model == dataclasses.replace(saved, hint_residual=False, prediction_type="epsilon",
                                                       image_size=32)
    main(base)  # without --init-from: the config's defaults
    assert seen["config"].model == NVSConfig()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_a_seed_gives_the_same_views_on_cuda_as_on_the_cpu(setup, tmp_path):
    """The shared initial noise is drawn on the CPU, as the cache key (which has no device) assumes."""
    images = {}
    for name, device, seed in (("cpu", "cpu", 0), ("cuda", "cuda", 0), ("other_seed", "cpu", 1)):
        run((*setup[:2], tmp_path / f"cache_{name}"), tmp_path / name, device=device, seed=seed)
        images[name] = iio.imread(tmp_path / name / "images" / "view_001.png").astype(int)
    assert int(abs(images["cpu"] - images["cuda"]).max()) <= 8  # rounding (TF32 convolutions), not other noise
    assert int(abs(images["cpu"] - images["other_seed"]).max()) > 8


def test_a_reference_given_other_intrinsics_is_resampled_to_them(setup, tmp_path, monkeypatch):
    """``reference_K``: the model gets the reference image reframed (same pose) and those intrinsics; the captured
    ones give the images of no ``reference_K``, other ones other images (another cache entry)."""
    data, _, _ = setup
    dataset = pipeline.OLATDataset(data)
    captured = dataset.intrinsics[0].double()
    image = ("images", "view_001.png")
    run(setup, tmp_path / "a")
    run(setup, tmp_path / "b", reference_K=captured, cache_dir=tmp_path / "cache")
    assert tmp_path.joinpath("a", *image).read_bytes() == tmp_path.joinpath("b", *image).read_bytes()
    batches = []
    call = pipeline.NovelViewPipeline.__call__
    monkeypatch.setattr(pipeline.NovelViewPipeline, "__call__",
                        lambda self, batch, *args, **kwargs: batches.append(batch) or call(self, batch, *args, **kwargs))
    zoomed = captured.clone()
    zoomed[0, 0] *= 2.0
    zoomed[1, 1] *= 2.0
    run(setup, tmp_path / "c", reference_K=zoomed, cache_dir=tmp_path / "cache")
    (batch,) = batches
    size = TINY["image_size"]
    seen_K = scale_intrinsics(zoomed, size / dataset.width)[None].float()
    reference, reference_K = load_rgba_views(dataset, [0], 1, size)
    assert torch.allclose(batch.reference_K, seen_K)
    assert torch.allclose(batch.reference, reframe(reference, reference_K, seen_K), atol=1e-6)
    assert not torch.allclose(batch.reference, reference, atol=1e-2)
    assert tmp_path.joinpath("a", *image).read_bytes() != tmp_path.joinpath("c", *image).read_bytes()
    for bad in (zoomed[:2], torch.full((3, 3), float("nan")), torch.diag(torch.tensor([0.0, 1.0, 1.0]))):
        with pytest.raises(ValueError, match=r"reference_K must be a finite \[3,3\] matrix with positive focal "
                                             r"lengths \(view 0 of .*transforms_train\.json\)"):
            run(setup, tmp_path / "d", reference_K=bad)
    assert not (tmp_path / "d").exists()  # refused before anything is written
