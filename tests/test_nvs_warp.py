"""Geometric warp hint of the novel-view model: known-answer splats, depth resizing, model/data/pipeline wiring."""

from __future__ import annotations

import json

import pytest
import torch
from tiny_models import TINY_NVS

from diamond_sss.data import OLATDataset
from diamond_sss.data.conventions import intrinsics_matrix
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.diffusion.common.schedulers import make_ddim_scheduler, make_ddpm_scheduler
from diamond_sss.diffusion.geometry import GeometryMaps, GeometrySource, StoredMapsGeometry
from diamond_sss.diffusion.geometry.base import GeometryError
from diamond_sss.diffusion.nvs import pipeline
from diamond_sss.diffusion.nvs.convert import free3d_config
from diamond_sss.diffusion.nvs.data import fixed_light_sequences, load_rgba_views, sample_batch
from diamond_sss.diffusion.nvs.model import NVSConfig, NVSModel
from diamond_sss.diffusion.nvs.pipeline import NovelViewPipeline
from diamond_sss.diffusion.nvs.warp import forward_warp, resize_depth

OBJECT = "finetune/torus_jade"


def w2c_from(rotation: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    """OpenCV world-to-camera of a camera at ``center`` with camera axes as the rows of ``rotation``."""
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ center.to(torch.float64)
    return w2c


@pytest.mark.parametrize("footprint", ["nearest", "bilinear"])
def test_identity_camera_returns_the_reference(footprint):
    g = torch.Generator().manual_seed(0)
    image = torch.rand(4, 6, 6, generator=g)
    depth = 1.0 + torch.rand(1, 6, 6, generator=g)
    K = intrinsics_matrix(5.0, 5.0, 3.0, 3.0)
    w2c = torch.eye(4)
    warped, valid = forward_warp(image, depth, w2c, K, w2c[None], K[None], 6, footprint=footprint)
    assert warped.shape == (1, 4, 6, 6) and valid.shape == (1, 1, 6, 6)
    assert bool(valid.all())
    torch.testing.assert_close(warped[0], image, atol=1e-6, rtol=0)


@pytest.mark.parametrize("footprint", ["nearest", "bilinear"])
def test_translating_past_a_fronto_parallel_plane_shifts_by_the_disparity(footprint):
    # plane z = 2, f = 8 px, camera moved b = 0.5 to the right: u' = u - f b / z = u - 2 px
    image = torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(1))
    depth = torch.full((1, 8, 8), 2.0)
    K = intrinsics_matrix(8.0, 8.0, 4.0, 4.0)
    target = w2c_from(torch.eye(3, dtype=torch.float64), torch.tensor([0.5, 0.0, 0.0]))
    warped, valid = forward_warp(image, depth, torch.eye(4), K, target[None], K[None], 8, footprint=footprint)
    torch.testing.assert_close(warped[0, :, :, :6], image[:, :, 2:], atol=1e-6, rtol=0)
    assert bool(valid[0, 0, :, :6].all()) and not bool(valid[0, 0, :, 6:].any())
    assert float(warped[0, :, :, 6:].abs().max()) == 0.0


@pytest.mark.parametrize("footprint", ["nearest", "bilinear"])
def test_the_nearer_of_two_points_on_one_target_ray_wins(footprint):
    # reference pixels (3, 2) at z = 2 and (4, 2) at z = 4 give P1 = (0.5, 0, 2) and P2 = (2, 0, 4); a camera
    # at (-1, 0, 0) looking along (0.6, 0, 0.8) sees both at its principal point, P1 at 2.5 and P2 at 5.
    image = torch.zeros(3, 5, 5)
    image[0, 2, 3] = 1.0  # near point: red
    image[1, 2, 4] = 1.0  # far point: green
    depth = torch.zeros(1, 5, 5)
    depth[0, 2, 3], depth[0, 2, 4] = 2.0, 4.0
    K = intrinsics_matrix(4.0, 4.0, 2.5, 2.5)
    rotation = torch.tensor([[0.8, 0.0, -0.6], [0.0, 1.0, 0.0], [0.6, 0.0, 0.8]], dtype=torch.float64)
    target = w2c_from(rotation, torch.tensor([-1.0, 0.0, 0.0]))
    warped, valid = forward_warp(image, depth, torch.eye(4), K, target[None], K[None], 5, footprint=footprint)
    torch.testing.assert_close(warped[0, :, 2, 2], torch.tensor([1.0, 0.0, 0.0]), atol=1e-6, rtol=0)
    assert int(valid.sum()) == 1
    depth[0, 2, 3] = 0.0  # without the near point the far one shows
    warped, _ = forward_warp(image, depth, torch.eye(4), K, target[None], K[None], 5, footprint=footprint)
    torch.testing.assert_close(warped[0, :, 2, 2], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6, rtol=0)


def test_points_behind_the_target_camera_or_outside_it_are_dropped():
    image, depth = torch.ones(4, 4, 4), torch.full((1, 4, 4), 1.0)
    K = intrinsics_matrix(4.0, 4.0, 2.0, 2.0)
    behind = w2c_from(torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64)), torch.zeros(3))
    aside = w2c_from(torch.eye(3, dtype=torch.float64), torch.tensor([50.0, 0.0, 0.0]))
    warped, valid = forward_warp(
        image, depth, torch.eye(4), K, torch.stack([behind, aside]), K.expand(2, 3, 3), 4
    )
    assert not bool(valid.any()) and float(warped.abs().max()) == 0.0


def test_background_and_unreadable_depths_add_nothing_however_the_colours_read():
    """Pixels without depth (0, or NaN from a damaged map) are masked, not dropped: they must weigh exactly nothing,
    even where the image holds NaN there (their masked contributions all land on the first output pixel)."""
    image = torch.rand(4, 8, 8, generator=torch.Generator().manual_seed(2))
    depth = torch.full((1, 8, 8), 2.0)
    depth[0, :, 5:] = 0.0
    K = intrinsics_matrix(8.0, 8.0, 4.0, 4.0)
    w2c = torch.eye(4)
    damaged_image, damaged_depth, hole = image.clone(), depth.clone(), depth.clone()
    damaged_image[:, :, 5:] = float("nan")
    damaged_depth[0, 3, 2] = float("nan")
    hole[0, 3, 2] = 0.0
    warped, valid = forward_warp(damaged_image, damaged_depth, w2c, K, w2c[None], K[None], 8)
    expected, expected_valid = forward_warp(image, hole, w2c, K, w2c[None], K[None], 8)
    assert bool(torch.isfinite(warped).all()) and torch.equal(valid, expected_valid)
    assert torch.equal(warped, expected) and float(valid[0, 0, 0, 0]) == 1.0 and float(valid[0, 0, 3, 2]) == 0.0
    torch.testing.assert_close(warped[0][:, valid[0, 0] > 0], image[:, valid[0, 0] > 0], atol=1e-6, rtol=0)


def test_resize_depth_min_pools_the_foreground():
    depth = torch.tensor(
        [[[1.0, 2.0, 0.0, 0.0], [3.0, 0.0, 0.0, 0.0], [0.0, 0.0, 5.0, 6.0], [0.0, 0.0, 7.0, 8.0]]]
    )
    torch.testing.assert_close(resize_depth(depth, 2), torch.tensor([[[1.0, 0.0], [0.0, 5.0]]]))
    assert resize_depth(depth, 4) is depth
    assert resize_depth(depth, 3).shape == (1, 3, 3)


def test_bad_warp_inputs_give_clear_errors():
    image, depth, K, w2c = torch.ones(4, 4, 4), torch.ones(1, 4, 4), torch.eye(3), torch.eye(4)
    with pytest.raises(ValueError, match="depth must have shape"):
        forward_warp(image, torch.ones(1, 3, 3), w2c, K, w2c[None], K[None], 4)
    with pytest.raises(ValueError, match="target_K"):
        forward_warp(image, depth, w2c, K, w2c[None], K.expand(2, 3, 3), 4)
    with pytest.raises(ValueError, match="footprint"):
        forward_warp(image, depth, w2c, K, w2c[None], K[None], 4, footprint="gaussian")
    with pytest.raises(ValueError, match="depth must have shape"):
        resize_depth(torch.ones(4, 4), 2)


def test_stored_depth_warps_a_real_view_onto_its_neighbours():
    dataset = OLATDataset(embedded_dataset("finetune/bust_marble"))
    views = [int(v) for v in torch.nonzero(dataset.presence[:, 0]).flatten()][:4]
    images, K = load_rgba_views(dataset, views, 0, dataset.width)
    depth = dataset.load_geometry_maps(views[0])[0].permute(2, 0, 1)
    warped, valid = forward_warp(
        images[0], depth, dataset.viewmats[views[0]], K[0], dataset.viewmats[views[1:]], K[1:], dataset.width
    )
    for i, truth in enumerate(images[1:]):
        keep = (valid[i, 0] > 0) & (warped[i, 3] > 0.99) & (truth[3] > 0.99) & (images[0, 3] > 0.99)
        assert int(keep.sum()) > 100
        warp_error = (warped[i, :3] - truth[:3]).abs()[:, keep].mean()
        copy_error = (images[0, :3] - truth[:3]).abs()[:, keep].mean()
        assert warp_error < 0.5 * copy_error


def test_config_channels_and_legacy_files():
    config = NVSConfig(**TINY_NVS)
    assert config.warp_hint and config.input_channels == 2 * 4 + 5
    assert NVSModel(config).unet.conv_in.in_channels == 13
    assert not free3d_config().warp_hint and free3d_config().input_channels == 8
    assert not NVSConfig.from_dict({"image_size": 16}).warp_hint  # written before the hint
    with pytest.raises(ValueError, match="pixel-space hint"):
        NVSConfig(space="latent")


@pytest.fixture(scope="module")
def warp_batch():
    sequences = fixed_light_sequences([embedded_dataset(OBJECT)], 32, with_depth=True)
    return sample_batch(sequences, 1, 2, torch.Generator().manual_seed(0))


def test_training_data_carries_the_reference_depth_and_the_model_trains_on_it(warp_batch):
    assert warp_batch.reference_depth.shape == (1, 1, 32, 32) and warp_batch.reference_K.shape == (1, 3, 3)
    assert float(warp_batch.reference_depth.max()) > 0 and float(warp_batch.reference_depth.min()) == 0
    torch.manual_seed(0)
    model = NVSModel(NVSConfig(**TINY_NVS, condition_dropout=0.0))
    hint = model.warp_hint(warp_batch)
    assert hint.shape == (2, 5, 16, 16) and 0 < float(hint[:, 4].mean()) < 1
    loss = model.training_loss(warp_batch, generator=torch.Generator().manual_seed(0))
    loss.backward()
    assert torch.isfinite(loss) and model.unet.conv_in.weight.grad[:, 8:].abs().sum() > 0
    out = NovelViewPipeline(model)(warp_batch, num_steps=1, generator=torch.Generator().manual_seed(0))
    assert out.rgb.shape == (2, 16, 16, 3)


def test_hint_residual_with_a_zero_residual_oracle_returns_the_warp(warp_batch):
    from diamond_sss.diffusion.nvs.model import hint_base

    model = NVSModel(NVSConfig(**TINY_NVS, hint_residual=True)).eval()
    alphas = make_ddim_scheduler(model.config.scheduler, model.config.sample_clip_range).alphas_cumprod

    def oracle(noisy, timesteps, reference, context, rays, num_views, hint=None):
        return noisy / (1 - alphas[timesteps].reshape(-1, 1, 1, 1)).sqrt()  # epsilon of a clean residual 0

    model.denoise = oracle
    out = NovelViewPipeline(model)(warp_batch, num_steps=5, generator=torch.Generator().manual_seed(0))
    out = torch.cat([out.rgb, out.alpha], dim=-1).permute(0, 3, 1, 2)
    expected = (hint_base(model.warp_hint(warp_batch)) + 1) / 2
    torch.testing.assert_close(out, expected, atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="needs warp_hint=True"):
        NVSConfig(warp_hint=False, hint_residual=True)


def test_warp_model_refuses_a_batch_without_depth(warp_batch):
    model = NVSModel(NVSConfig(**TINY_NVS))
    warp_batch = type(warp_batch)(**{**vars(warp_batch), "reference_depth": None})
    with pytest.raises(ValueError, match="reference_depth"):
        NovelViewPipeline(model)(warp_batch, num_steps=1)


def test_training_data_without_depth_maps_is_refused(tmp_path):
    from diamond_sss.data.analytic import make_capture

    make_capture(tmp_path, views=3, lights=1, size=8)
    with pytest.raises(ValueError, match="no stored depth maps"):
        fixed_light_sequences([tmp_path], 8, with_depth=True)


class RelativeOnly(GeometrySource):
    """A source with relative depth only, like Depth Anything."""

    def maps(self, dataset, view, image, mask) -> GeometryMaps:
        return GeometryMaps(nearness=mask, normals=torch.zeros(*mask.shape[:2], 3), mask=mask)

    def key(self) -> dict:
        return {"kind": "relative-only"}


class ScaledMaps(StoredMapsGeometry):
    """Stored maps with a different identity (a different cache key)."""

    def key(self) -> dict:
        return {"kind": "maps-copy"}


def test_generation_with_the_warp_hint_needs_metric_depth_and_keys_the_cache_by_source(tmp_path):
    torch.manual_seed(0)
    model_dir = NVSModel(NVSConfig(**TINY_NVS)).save(tmp_path / "model")
    data = embedded_dataset(OBJECT)

    def run(out, geometry):
        return pipeline.generate_novel_views(
            data,
            tmp_path / out,
            0,
            0,
            [1, 2],
            model_dir=model_dir,
            steps=1,
            cache_dir=tmp_path / "cache",
            geometry=geometry,
        )

    with pytest.raises(GeometryError, match="geometry source"):
        run("a", None)
    with pytest.raises(GeometryError, match="'relative-only' gives only relative depth"):
        run("a", RelativeOnly())
    manifest = json.loads(run("a", StoredMapsGeometry()).read_text())
    assert [m["view"] for m in manifest] == [1, 2]
    run("b", ScaledMaps())
    assert len(list((tmp_path / "cache").glob("*/*"))) == 2  # one cache entry per geometry source
    dataset = OLATDataset(data)
    cameras = pipeline.parse_targets("1,3", dataset)
    hint = pipeline.warp_reference_views(dataset, 0, 0, cameras, StoredMapsGeometry(), NVSConfig(**TINY_NVS))
    truth = load_rgba_views(dataset, [1, 3], 0, dataset.width)[0][:, 3]
    overlap = ((hint[:, 3] > 0.5) & (truth > 0.5)).sum() / ((hint[:, 3] > 0.5) | (truth > 0.5)).sum()
    assert hint.shape == (2, 4, 64, 64) and float(overlap) > 0.5


def test_camera_geometry_stays_float32_under_bf16_autocast(warp_batch):
    """The fine-tune's ``--mixed-precision bf16``: rays, pose and warp hint as in float32, and the loss trains."""
    torch.manual_seed(0)
    model = NVSModel(NVSConfig(**TINY_NVS, hint_residual=True))
    reference = model.encode(warp_batch.reference)
    full = (*model.conditioning(warp_batch, reference), model.warp_hint(warp_batch))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = (*model.conditioning(warp_batch, reference), model.warp_hint(warp_batch))
        loss = model.training_loss(warp_batch, generator=torch.Generator().manual_seed(0))
    for a, b in zip(full, mixed, strict=True):
        assert b.dtype == torch.float32
        torch.testing.assert_close(a, b, atol=0, rtol=0)
    loss.backward()
    assert torch.isfinite(loss) and model.unet.conv_in.weight.grad.abs().sum() > 0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("precision", [None, torch.bfloat16], ids=["float32", "bf16"])
def test_a_training_step_on_cuda_never_waits_for_the_gpu(precision):
    """Batch copy, warp hint, loss and backward pass with CUDA's sync debugging set to raise on any host sync,
    in float32 and in the prior's bf16 autocast."""
    from diamond_sss.diffusion.nvs.train import _to_device

    config = NVSConfig(**{**TINY_NVS, "hint_residual": True})
    model = NVSModel(config).cuda()
    sequences = fixed_light_sequences([embedded_dataset(OBJECT)], config.warp_source_size, with_depth=True)
    generator = torch.Generator(device="cuda").manual_seed(0)
    scheduler = make_ddpm_scheduler(config.scheduler)  # made once, as the fine-tune does: its tables move once
    cuda = torch.device("cuda")

    def step(seed: int) -> torch.Tensor:
        batch = sample_batch(sequences, 2, 2, torch.Generator().manual_seed(seed))
        with torch.autocast("cuda", dtype=precision or torch.float32, enabled=precision is not None):
            loss = model.training_loss(_to_device(batch, cuda), generator=generator, scheduler=scheduler)
        loss.backward()
        return loss

    step(0)  # warm-up
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        loss = step(1)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert torch.isfinite(loss).item()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA GPU")])])
def test_sorted_splat_sums_match_index_add_and_repeat_to_the_bit(device):
    """The sorted per-pixel sums (the warp's on CUDA; here on each device): ``index_add``'s to float64 round-off on
    rows of very different scales, empty bins exactly 0, the same bits again under deterministic algorithms."""
    from diamond_sss.diffusion.common.runtime import kernel_settings
    from diamond_sss.diffusion.nvs.warp import _bin_sums, _sorted_bin_sums

    generator = torch.Generator().manual_seed(0)
    index = torch.randint(0, 5000, (200_000,), generator=generator)
    index[index == 7] = 8  # one bin nothing reaches
    scales = torch.tensor([[1.0], [1e-9], [1e6]], dtype=torch.float64)
    values = torch.rand(3, index.numel(), generator=generator, dtype=torch.float64) * scales
    expected = torch.zeros(3, 5000, dtype=torch.float64).index_add(1, index, values)
    index, values = index.to(device), values.to(device)
    with kernel_settings(deterministic=True):
        sums = _sorted_bin_sums(index, values, 5000)
        again = _sorted_bin_sums(index, values, 5000)
    torch.testing.assert_close(sums.cpu(), expected, rtol=1e-12, atol=0)
    assert (sums[:, 7] == 0).all() and torch.equal(sums, again)
    torch.testing.assert_close(_bin_sums(index, values, 5000).cpu(), expected, rtol=1e-12, atol=0)
    values[1, index == 9] = torch.nan  # a non-finite value spoils its bin alone, as with index_add
    spoiled = _sorted_bin_sums(index, values, 5000).cpu()
    assert spoiled[1, 9].isnan() and not spoiled[1, :9].isnan().any() and not spoiled[1, 10:].isnan().any()
    torch.testing.assert_close(spoiled[[0, 2]], expected[[0, 2]], rtol=1e-12, atol=0)
