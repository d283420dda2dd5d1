"""Generated images supervise the reconstruction at the resolution they were made at (issue 57, item 3).

A diffusion model's image of a larger capture is written at the model's size, read with its camera's intrinsics
scaled to that size, matched to the capture's camera, and compared with the full-size render area-downsampled to
its size; a capture whose images all have the render's size trains exactly as before.
"""

from __future__ import annotations

import copy
from dataclasses import fields

import imageio.v3 as iio
import pytest
import torch
import torch.nn.functional as F
from test_relight_model import tiny_model
from tiny_models import TINY_NVS

from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture
from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.diffusion.common.cache import OutputCache
from diamond_sss.diffusion.geometry import StoredMapsGeometry
from diamond_sss.diffusion.nvs import pipeline
from diamond_sss.diffusion.nvs.model import NVSConfig, NVSModel
from diamond_sss.diffusion.relight.inference import relight_view, write_relit
from diamond_sss.losses.photometric import dssim_per_image, l1_per_image
from diamond_sss.losses.regularizers import mask_bce_loss
from diamond_sss.pipeline.capture import GeneratedImage, write_capture
from diamond_sss.scene.model import SceneRender
from diamond_sss.shading.deferred import GBuffer, ShadingResult
from diamond_sss.training.lattice import unify_lattices
from diamond_sss.training.objective import image_objective
from diamond_sss.training.overrides import make_config
from diamond_sss.training.trainer import ImageSource, Trainer, area_downsample_render

TINY = {"num_gaussians": 300, "lambda_lpips": 0.0, "raytrace_gaussians": 64, "mv_pixels_per_pair": 32,
        "mv_pairs_per_step": 2, "densify": False, "log_every": 1, "image_log_every": 1000, "device": "cpu"}


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """The same 4-view, 2-light lattice at 128 px (the capture) and at 64 px (as a diffusion model made it)."""
    root = tmp_path_factory.mktemp("sizes")
    make_capture(root / "full", views=4, lights=2, size=128)
    make_capture(root / "model", views=4, lights=2, size=64)
    return root


def test_cameras_of_two_sizes_unify_to_one_view(captures, tmp_path):
    full, small = OLATDataset(captures / "full"), OLATDataset(captures / "model")
    assert torch.equal(small.intrinsics[:, :2] * 2, full.intrinsics[:, :2])  # the same cameras, in 64 px
    union = unify_lattices([full, small])
    assert union.view_maps == [[0, 1, 2, 3], [0, 1, 2, 3]] and union.num_views == 4
    assert union.view_sizes == [[(128, 128)] * 4, [(64, 64)] * 4] and (union.width, union.height) == (128, 128)
    torch.testing.assert_close(union.Ks, full.intrinsics, rtol=1e-6, atol=0.0)
    make_capture(tmp_path / "new", views=2, lights=2, size=64, camera_offset=1.1)  # two cameras off the lattice
    new = OLATDataset(tmp_path / "new")
    union = unify_lattices([full, new])
    assert union.view_maps[1] == [4, 5] and union.view_sizes[1] == [(64, 64)] * 2
    torch.testing.assert_close(union.Ks[4, :2], new.intrinsics[0, :2] * 2)  # in pixels of the 128 px render
    with pytest.raises(ValueError, match=r"view 0's images are 128x128, larger than the capture .* 64x64"):
        unify_lattices([small, full])


def test_area_downsampling_averages_premultiplied_maps_and_weighs_the_others_by_alpha():
    """A 2x2 block seen by one pixel: alpha and radiance (premultiplied) are block means; depth (alpha-normalised)
    the alpha-weighted mean, 0 where no pixel of the block is covered."""
    alpha = torch.tensor([[1.0, 0.5, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0]])[None, ..., None]  # a covered, an empty block
    depth = torch.tensor([[2.0, 4.0, 7.0, 7.0], [4.0, 9.0, 7.0, 7.0]])[None, ..., None]
    maps = {f.name: torch.zeros(1, 2, 4, 1 if f.name in ("roughness", "metallic", "subsurface", "visibility",
                                                         "incident") else 3) for f in fields(GBuffer)}
    gbuffer = GBuffer(**{**maps, "depth": depth, "alpha": alpha})
    radiance = alpha * torch.tensor([0.2, 0.4, 0.6])
    shading = ShadingResult(radiance=radiance, pbr=radiance, diffuse=radiance, specular=radiance, residual=radiance,
                            points=depth.expand(-1, -1, -1, 3))
    low = area_downsample_render(SceneRender(shading, gbuffer, None), torch.tensor([0]), 1, 2)
    torch.testing.assert_close(low.gbuffer.alpha[0, 0, :, 0], torch.tensor([0.5, 0.0]))
    torch.testing.assert_close(low.radiance[0, 0, 0], 0.5 * torch.tensor([0.2, 0.4, 0.6]))
    torch.testing.assert_close(low.gbuffer.depth[0, 0, :, 0], torch.tensor([(2.0 + 2.0 + 2.0) / 2.0, 0.0]))
    torch.testing.assert_close(low.shading.points[0, 0, 0], torch.full((3,), 3.0))


def _mixed_step(trainer: Trainer) -> int:
    """The first step whose batch holds images of both sources."""
    return next(step for step in range(50) if {s for s, _ in trainer.draw_batch(step)[0]} == {0, 1})


def test_a_smaller_source_is_compared_with_the_area_downsampled_render(captures):
    """Known answer: the step's photometric and mask terms equal ``(1/B) sum_b w_b E_b`` with each 64 px image's
    ``E_b`` taken against the 128 px render's 2x2 block means (radiance and alpha), over a random background."""
    full, small = OLATDataset(captures / "full"), OLATDataset(captures / "model")
    cfg = make_config("diamond", overrides={**TINY, "batch_size": 4, "random_background": True, "iterations": 3})
    sources = [ImageSource(full.subset(range(0, 8, 2))), ImageSource(small.subset(range(1, 8, 2)), 0.5)]
    trainer = Trainer(cfg, sources, None, show_progress=False)
    scene = trainer.build_scene()
    before = copy.deepcopy(scene)
    step = _mixed_step(trainer)
    terms = trainer.training_step(scene, trainer.build_optimizers(scene), {}, step)
    assert {(g.width, g.height) for g in trainer._batch_groups} == {(128, 128), (64, 64)}
    assert {"mv_silhouette", "mv_depth"} <= set(terms)  # the multi-view terms see the full-size render
    assert all(torch.isfinite(value) for value in terms.values())

    picks, target, light_pos, light_rgb = trainer.draw_batch(step)
    with torch.no_grad():
        render = before.render(target.viewmats, target.Ks, 128, 128, light_pos, light_rgb)
    photometric, mask = [], []
    lam = cfg.losses.lambda_dssim
    for b, (source, index) in enumerate(picks):
        sample = sources[source].dataset.load(index)
        radiance, alpha = render.radiance[b : b + 1], render.gbuffer.alpha[b : b + 1]
        if sample.rgb.shape[0] == 64:
            radiance, alpha = (F.avg_pool2d(x.permute(0, 3, 1, 2), 2).permute(0, 2, 3, 1) for x in (radiance, alpha))
        background = target.background[b]
        pred = linear_to_srgb(radiance + (1.0 - alpha) * background)
        observed = linear_to_srgb((sample.rgb + (1.0 - sample.mask) * background)[None])
        error = (1.0 - lam) * l1_per_image(pred, observed) + lam * dssim_per_image(pred, observed)
        photometric.append(sources[source].weight * error[0])
        mask.append(cfg.losses.lambda_mask * mask_bce_loss(alpha, sample.mask[None]))
    torch.testing.assert_close(terms["photometric"], torch.stack(photometric).mean(), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(terms["mask"], torch.stack(mask).mean(), rtol=1e-5, atol=1e-7)

    result = Trainer(cfg, sources, None, show_progress=False).run()
    assert result.steps == 3 and all(torch.isfinite(torch.tensor(h["total"])) for h in result.history)


def test_a_capture_of_one_size_trains_as_before(captures, tmp_path):
    """With every image at the render's size (a 64 px capture and generated images at 64 px) the step's terms are
    those of the one-group objective to the bit, and the union keeps the capture's cameras unchanged."""
    real = OLATDataset(captures / "model")
    picks = [real.observations[i] for i in (1, 4, 6)]
    write_capture(tmp_path, "gen", real, [GeneratedImage(o.view, o.light, o.image_path) for o in picks])
    sources = [ImageSource(real.subset([0, 2, 3, 5])), ImageSource(OLATDataset(tmp_path, "gen"), 0.5)]
    cfg = make_config("diamond", overrides={**TINY, "batch_size": 3, "random_background": True})
    trainer = Trainer(cfg, sources, None, show_progress=False)
    assert torch.equal(trainer.union.Ks[:4], real.intrinsics) and trainer.union.view_maps[1] == [0, 1, 2, 3]
    scene = trainer.build_scene()
    before = copy.deepcopy(scene)
    step = _mixed_step(trainer)
    terms = trainer.training_step(scene, trainer.build_optimizers(scene), {}, step)
    assert len(trainer._batch_groups) == 1
    _, target, light_pos, light_rgb = trainer.draw_batch(step)
    with torch.no_grad():
        render = before.render(target.viewmats, target.Ks, 64, 64, light_pos, light_rgb)
    expected = image_objective(render, target, cfg, None)
    assert all(torch.equal(terms[name], value) for name, value in expected.items())


def test_generated_images_are_written_at_the_models_size(captures, tmp_path):
    """A 16 px novel-view model on a 64 px capture writes 16 px images; their capture declares the camera at
    16 px (intrinsics / 4), which joins the capture's view. A 16 px relighting model on a 64 px capture writes
    16 px images with the source mask area-downsampled to 16 px."""
    torch.manual_seed(0)
    model_dir = NVSModel(NVSConfig(**{**TINY_NVS, "warp_hint": False})).save(tmp_path / "nvs")
    real = OLATDataset(captures / "model")
    manifest = pipeline.generate_novel_views(captures / "model", tmp_path / "out", 0, 1, [2, 3], model_dir=model_dir,
                                             steps=2, cache_dir=tmp_path / "cache")
    images = [tmp_path / "out" / "images" / f"view_00{v}.png" for v in (2, 3)]
    assert manifest.is_file() and {iio.imread(path).shape for path in images} == {(16, 16, 4)}
    write_capture(tmp_path, "nvs", real, [GeneratedImage(v, 1, path) for v, path in zip((2, 3), images)])
    generated = OLATDataset(tmp_path, "nvs")
    assert [(generated.cameras[v].width, generated.cameras[v].height) for v in range(4)] == [(64, 64), (64, 64),
                                                                                               (16, 16), (16, 16)]
    torch.testing.assert_close(generated.intrinsics[2, :2] * 4, real.intrinsics[2, :2])
    assert generated.load(0).rgb.shape == (16, 16, 3)
    assert unify_lattices([real, generated]).view_maps[1] == [0, 1, 2, 3]
    # real 64 px images beside 16 px ones in one capture (the relighting stage's sources): the same bounds
    beside = [GeneratedImage(0, 1, images[0]), GeneratedImage(1, 1, real.observations[3].image_path)]
    write_capture(tmp_path, "mixed", real, beside)
    mixed = OLATDataset(tmp_path, "mixed")
    assert (mixed.cameras[0].width, mixed.cameras[1].width) == (16, 64)
    assert mixed.bounds.radius == pytest.approx(real.bounds.radius, rel=1e-5)

    capture = OLATDataset(embedded_dataset("finetune/torus_jade"))
    view = next(v for v in range(capture.num_views) if int(capture.presence[v].sum()) >= 2)
    lights = [int(i) for i in torch.nonzero(capture.presence[view])[:, 0]]
    source = capture.load(capture.observation_index(view, lights[0]))
    assert source.rgb.shape[:2] == (64, 64)
    relit = relight_view(tiny_model().eval(), capture, view, lights[0], lights[1:2], StoredMapsGeometry(),
                         OutputCache(tmp_path / "relight_cache"), num_steps=1, samples=1)
    expected_mask = F.avg_pool2d(source.mask.permute(2, 0, 1)[None], 4)[0].permute(1, 2, 0)
    assert relit[0].rgb.shape == (16, 16, 3)
    torch.testing.assert_close(relit[0].mask, expected_mask, atol=0.5 / 255 + 1e-6, rtol=0.0)  # 8-bit alpha
    written = write_relit(tmp_path / "relit", relit)
    assert written.is_file() and iio.imread(tmp_path / "relit" / "images" / f"v{view:03d}_l{lights[1]:03d}.png"
                                            ).shape == (16, 16, 4)
