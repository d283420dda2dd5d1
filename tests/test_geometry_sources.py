"""Geometry sources of the relighting model: stored maps, tiny random Depth Anything / Marigold, parsing."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from tiny_models import tiny_sd_unet, tiny_vae

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.diffusion.geometry import (
    CombinedGeometry,
    DepthAnythingGeometry,
    MarigoldGeometry,
    StoredMapsGeometry,
    geometry_source,
)
from diamond_sss.diffusion.geometry.base import GeometryError, normals_from_nearness


@pytest.fixture(scope="module")
def view_sample():
    dataset = OLATDataset(embedded_dataset("finetune/torus_jade"))
    view = next(v for v in range(dataset.num_views) if dataset.has_geometry_maps(v))
    index = next(i for i, o in enumerate(dataset.observations) if o.view == view)
    sample = dataset.load(index)
    return dataset, view, sample.rgb, sample.mask


def check_maps(maps, mask):
    keep = mask[..., 0] > 0.5
    assert maps.nearness.shape == mask.shape and maps.normals.shape == mask.shape[:2] + (3,)
    assert float(maps.nearness.min()) >= 0.0 and float(maps.nearness.max()) <= 1.0
    assert float(maps.nearness[~keep].abs().max()) == 0.0
    assert torch.allclose(maps.normals[keep].norm(dim=-1), torch.ones(int(keep.sum())), atol=1e-4)


def test_normals_from_a_nearness_ramp():
    mask = torch.ones(8, 8, 1)
    slope = 0.05
    nearness = (torch.arange(8.0) * slope).expand(8, 8)[..., None]
    normals = normals_from_nearness(nearness, mask)
    scale = 8.0  # sqrt of the mask area
    expected = torch.nn.functional.normalize(torch.tensor([-slope * scale, 0.0, -1.0]), dim=0)
    assert torch.allclose(normals[3, 3], expected, atol=1e-5)


def test_stored_maps_face_the_camera(view_sample):
    dataset, view, rgb, mask = view_sample
    maps = StoredMapsGeometry().maps(dataset, view, rgb, mask)
    check_maps(maps, mask)
    keep = mask[..., 0] > 0.5
    # Visible surfaces face the camera: OpenCV z points away from it, so n_z < 0 on average.
    assert float(maps.normals[keep][:, 2].mean()) < -0.3
    assert float(maps.nearness.max()) == pytest.approx(1.0)


def test_stored_maps_carry_metric_depth(view_sample):
    dataset, view, rgb, mask = view_sample
    maps = StoredMapsGeometry().maps(dataset, view, rgb, mask)
    torch.testing.assert_close(maps.depth, dataset.load_geometry_maps(view)[0])
    assert float(maps.depth.max()) > 0


def test_stored_maps_missing_raise(view_sample, tmp_path):
    _, view, rgb, mask = view_sample
    root = embedded_dataset("finetune/torus_jade")
    shutil.copytree(root, tmp_path / "data")
    transforms = json.loads((root / "transforms_train.json").read_text())
    for frame in transforms["frames"]:
        frame.pop("depth_path", None)
        frame.pop("normal_path", None)
    (tmp_path / "data" / "transforms_train.json").write_text(json.dumps(transforms))
    with pytest.raises(GeometryError, match="no stored depth/normal maps"):
        StoredMapsGeometry().maps(OLATDataset(tmp_path / "data"), view, rgb, mask)
    with pytest.raises(GeometryError, match="no stored depth/normal maps"):
        StoredMapsGeometry().view_key(OLATDataset(tmp_path / "data"), view)


def test_stored_maps_key_the_content_of_the_views_maps(view_sample, tmp_path):
    import numpy as np

    _, view, _, _ = view_sample
    shutil.copytree(embedded_dataset("finetune/torus_jade"), tmp_path / "data")
    dataset = OLATDataset(tmp_path / "data")
    source = StoredMapsGeometry()
    first = source.view_key(dataset, view)
    assert first["kind"] == "maps" and source.view_key(OLATDataset(tmp_path / "data"), view) == first
    assert source.view_key(dataset, view + 1) != first
    keys = [first]
    for name in ("depth", "normal"):
        path = tmp_path / "data" / "train" / f"v{view:03d}_{name}.npy"
        values = np.load(path)
        values[values.shape[0] // 2] *= 0.5
        np.save(path, values)
        keys.append(source.view_key(OLATDataset(tmp_path / "data"), view))
    assert len({json.dumps(key) for key in keys}) == 3  # each edited map is another key
    assert source.key() == {"kind": "maps"}


def test_parse_rejects_unusable_sources(tmp_path):
    with pytest.raises(GeometryError, match="not an existing run folder"):
        geometry_source(str(tmp_path / "nothing"))
    with pytest.raises(GeometryError, match="no model.safetensors"):
        geometry_source(str(tmp_path))
    with pytest.raises(GeometryError, match="does not exist"):
        geometry_source(f"marigold:{tmp_path / 'missing'}")
    with pytest.raises(GeometryError, match="no geometry source"):
        geometry_source("")
    assert isinstance(geometry_source("maps"), StoredMapsGeometry)


@pytest.fixture(scope="module")
def tiny_depth_anything(tmp_path_factory):
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    torch.manual_seed(0)
    backbone = Dinov2Config(
        hidden_size=32,
        num_hidden_layers=4,
        num_attention_heads=2,
        intermediate_size=64,
        patch_size=14,
        image_size=28,
        out_features=["stage1", "stage2", "stage3", "stage4"],
        reshape_hidden_states=False,
    )
    config = DepthAnythingConfig(
        backbone_config=backbone,
        reassemble_hidden_size=32,
        neck_hidden_sizes=[8, 16, 16, 32],
        fusion_hidden_size=16,
        head_hidden_size=8,
        patch_size=14,
    )
    path = tmp_path_factory.mktemp("depth_anything")
    DepthAnythingForDepthEstimation(config).save_pretrained(path)
    return path


@pytest.fixture(scope="module")
def tiny_marigold(tmp_path_factory):
    from diffusers import DDIMScheduler, MarigoldNormalsPipeline

    torch.manual_seed(0)
    unet = tiny_sd_unet(in_channels=8, cross_attention_dim=8)
    vae = tiny_vae()
    scheduler = DDIMScheduler(prediction_type="v_prediction")
    pipe = MarigoldNormalsPipeline(
        unet=unet,
        vae=vae,
        scheduler=scheduler,
        text_encoder=None,
        tokenizer=None,
        prediction_type="normals",
        default_denoising_steps=1,
        default_processing_resolution=32,
    )
    path = tmp_path_factory.mktemp("marigold")
    pipe.save_pretrained(path)
    return path


def test_tiny_depth_anything_wiring(view_sample, tiny_depth_anything):
    dataset, view, rgb, mask = view_sample
    source = geometry_source(f"depth-anything:{tiny_depth_anything}")
    assert isinstance(source, DepthAnythingGeometry)
    source.input_size = 28
    maps = source.maps(dataset, view, rgb, mask)
    check_maps(maps, mask)
    assert maps.depth is None  # relative depth only: no warp hint from it
    assert source.key()["hash"] == DepthAnythingGeometry(tiny_depth_anything).key()["hash"]


def test_tiny_marigold_wiring(view_sample, tiny_marigold, tiny_depth_anything):
    dataset, view, rgb, mask = view_sample
    source = geometry_source(f"marigold:{tiny_marigold}")
    assert isinstance(source, MarigoldGeometry)
    maps = source.maps(dataset, view, rgb, mask)
    check_maps(maps, mask)
    first = maps.normals.clone()
    assert torch.equal(source.maps(dataset, view, rgb, mask).normals, first)  # seeded
    combined = geometry_source(f"depth-anything:{tiny_depth_anything}+marigold:{tiny_marigold}")
    assert isinstance(combined, CombinedGeometry)
    combined.depth.input_size = 28
    check_maps(combined.maps(dataset, view, rgb, mask), mask)


def test_rendered_from_a_reconstruction_run(tmp_path):
    from diamond_sss.data.analytic import make_capture
    from diamond_sss.diffusion.geometry import RenderedGeometry
    from diamond_sss.training.run import train_from_preset

    make_capture(tmp_path / "data", views=4, lights=2, size=16)
    overrides = {
        "iterations": 2,
        "num_gaussians": 200,
        "batch_size": 2,
        "lambda_lpips": 0.0,
        "densify": False,
        "raytrace_gaussians": 32,
        "log_every": 1,
        "image_log_every": 1000,
        "device": "cpu",
    }
    train_from_preset(tmp_path / "data", tmp_path / "run", preset="sss3dgs", overrides=overrides,
                      show_progress=False)
    source = geometry_source(str(tmp_path / "run"))
    assert isinstance(source, RenderedGeometry)
    dataset = OLATDataset(tmp_path / "data")
    sample = dataset.load(0)
    maps = source.maps(dataset, sample.view, sample.rgb, sample.mask)
    assert maps.nearness.shape == (16, 16, 1) and maps.normals.shape == (16, 16, 3)
    assert bool(torch.isfinite(maps.normals).all()) and float(maps.nearness.max()) <= 1.0
    assert float(maps.nearness.max()) > 0.5  # the object is rendered inside the mask
    assert source.key() == RenderedGeometry(tmp_path / "run").key()
