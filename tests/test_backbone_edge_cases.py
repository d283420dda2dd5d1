"""Edge cases of the backbone: the random background on both sides of the photometric terms, config checks,
the light calibration's subsample, empty and damaged PLY files, checkpoints without their average, the multi-view
targets' intrinsics and the view-pair sampler the trainer uses."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image
from plyfile import PlyData, PlyElement

from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture
from diamond_sss.errors import DamagedFileError, DataError
from diamond_sss.gaussians import PARAM_SHAPES, GaussianModel, export_ply, import_ply, load_points3d_ply
from diamond_sss.gaussians.init import initial_points
from diamond_sss.losses.multiview import sample_view_pairs
from diamond_sss.losses.regularizers import masked_mean, raytrace_visibility_loss
from diamond_sss.training.checkpoint import load_checkpoint, resume_checkpoint, save_checkpoint
from diamond_sss.training.objective import TargetBatch, image_objective
from diamond_sss.training.overrides import make_config
from diamond_sss.training.trainer import ImageSource, Trainer, strided_quantile

PHOTOMETRIC_ONLY = {"lambda_lpips": 0.0, "lambda_mask": 0.0, "lambda_mask_entropy": 0.0, "lambda_normal": 0.0,
                    "lambda_incident_light": 0.0, "lambda_enh": 0.0, "lambda_base_color": 0.0,
                    "lambda_base_color_smooth": 0.0, "lambda_metallic_smooth": 0.0, "lambda_roughness_smooth": 0.0,
                    "lambda_subsurfacedness_smooth": 0.0, "photometric_space": "linear"}


def _batch(alpha: torch.Tensor, background: torch.Tensor | None):
    generator = torch.Generator().manual_seed(0)
    mask = torch.zeros(2, 16, 16, 1)
    mask[:, 4:12, 3:13] = 1.0
    rgb = torch.rand(2, 16, 16, 3, generator=generator) * mask
    render = SimpleNamespace(radiance=rgb, gbuffer=SimpleNamespace(alpha=alpha))
    eye = torch.eye(4).expand(2, 4, 4)
    target = TargetBatch(rgb=rgb, mask=mask, weights=torch.ones(2), viewmats=eye, Ks=eye[:, :3, :3],
                         background=background)
    return render, target, mask


@pytest.mark.parametrize("dssim", [0.0, 0.492])
def test_a_render_equal_to_the_target_matches_it_over_a_background(dssim):
    background = torch.tensor([0.9, 0.2, 0.6]).reshape(1, 1, 1, 3).repeat(2, 1, 1, 1)
    mask = _batch(torch.zeros(2, 16, 16, 1), None)[2]
    render, target, _ = _batch(mask.clone(), background)  # alpha = mask, radiance = rgb
    cfg = make_config("diamond", overrides={**PHOTOMETRIC_ONLY, "lambda_dssim": dssim})
    terms = image_objective(render, target, cfg, None)
    assert terms.keys() == {"photometric"} and float(terms["photometric"]) < 1e-6


def test_the_background_reaches_the_predicted_alpha():
    background = torch.tensor([0.8, 0.4, 0.2]).reshape(1, 1, 1, 3).repeat(2, 1, 1, 1)
    alpha = torch.full((2, 16, 16, 1), 0.5, requires_grad=True)
    render, target, mask = _batch(alpha, background)
    cfg = make_config("diamond", overrides={**PHOTOMETRIC_ONLY, "lambda_dssim": 0.0})
    loss = image_objective(render, target, cfg, None)["photometric"]
    # |(rgb + 0.5 b) - (rgb + (1 - M) b)| = 0.5 b inside the mask and outside it alike
    torch.testing.assert_close(loss, 0.5 * background.mean())
    loss.backward()
    # d/d alpha of the mean of |(M - alpha) b_c| over N = 2 * 16 * 16 * 3 values: -sum_c b_c / N inside the mask
    # (M - alpha > 0), +sum_c b_c / N outside it: more alpha darkens the background where the target shows it
    torch.testing.assert_close(alpha.grad, (1 - 2 * mask) * (0.8 + 0.4 + 0.2) / (2 * 16 * 16 * 3))
    plain_alpha = torch.full((2, 16, 16, 1), 0.5, requires_grad=True)
    render, target, _ = _batch(plain_alpha, None)
    assert not image_objective(render, target, cfg, None)["photometric"].requires_grad  # over black: no alpha


@pytest.mark.parametrize("key", ["densify.reset_every", "runtime.image_log_every", "raytrace.gaussians",
                                 "multiview.pairs_per_step", "multiview.pixels_per_pair", "multiview.nearest_k"])
def test_sizes_and_periods_without_an_off_value_must_be_positive(key):
    with pytest.raises(ValueError, match=f"config key '{key}' must be positive, got 0"):
        make_config(sets=[f"{key}=0"])


def test_the_position_rates_are_both_positive_or_both_zero():
    for key, other in (("lr.position_final", "lr.position_init"), ("lr.position_init", "lr.position_final")):
        with pytest.raises(ValueError, match=f"config key '{key}' must be positive when the other position rate"):
            make_config(sets=[f"{key}=0"])
        assert make_config(sets=[f"{key}=0", f"{other}=0"]).get(key) == 0.0  # frozen positions
    assert make_config(sets=["raytrace.directions=0"]).raytrace.directions == 0  # the lights alone: allowed


def test_strided_quantile_takes_every_image():
    values = torch.cat([torch.zeros(1_000_000), torch.ones(2_000_000)])  # the first 1M values hold no 1
    assert strided_quantile(values, 0.99) == 1.0
    ramp = torch.arange(2_000_000, dtype=torch.float64)  # stride 2: 0, 2, ..., 1999998
    assert strided_quantile(ramp, 0.5) == pytest.approx(999_999.0)
    small = torch.rand(5000, generator=torch.Generator().manual_seed(1))
    assert strided_quantile(small, 0.99) == float(torch.quantile(small, 0.99))


def test_masked_mean_of_nothing_is_zero_with_a_graph():
    empty = torch.empty(0, 1, requires_grad=True)
    value = masked_mean(empty, None)
    assert value.item() == 0.0 and value.requires_grad
    value.backward()
    assert raytrace_visibility_loss(torch.empty(0, 5), torch.empty(0, 5)).item() == 0.0
    assert masked_mean(torch.tensor([1.0, 2.0, 6.0]), None).item() == 3.0


def test_an_empty_model_round_trips_through_ply(tmp_path):
    empty = GaussianModel({name: torch.zeros(0, *shape) for name, shape in PARAM_SHAPES.items()})
    back = import_ply(export_ply(empty, tmp_path / "empty.ply"))
    assert back.num_gaussians == 0
    assert {k: v.shape for k, v in back.state_tensors().items()} == {k: v.shape for k, v in empty.state_tensors().items()}


def _write_points(path, count: int) -> None:
    vertices = np.zeros(count, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    vertices["x"] = np.arange(count)
    PlyData([PlyElement.describe(vertices, "vertex")], text=False).write(str(path))


@pytest.mark.parametrize("keep", [0.9, 0.3])  # a cut in the vertices, a cut in the header
def test_a_truncated_ply_is_a_damaged_file_naming_it(tmp_path, keep):
    path = tmp_path / "points3d.ply"
    _write_points(path, 10)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    for read in (load_points3d_ply, import_ply):
        with pytest.raises(DamagedFileError, match=f"{path}: damaged or truncated"):
            read(path)


def test_a_points3d_ply_of_three_points_is_named(tmp_path):
    path = tmp_path / "points3d.ply"
    _write_points(path, 3)
    kwargs = {"num_points": 100, "bounds_center": torch.zeros(3), "bounds_radius": 1.0, "points3d_path": path}
    with pytest.raises(DataError, match=f"{path}: 3 points; the initial Gaussians need at least 4"):
        initial_points(**kwargs)
    _write_points(path, 4)
    assert initial_points(**kwargs).points.shape == (4, 3)


def _save(run_dir, step: int, average: bool):
    weight = torch.nn.Parameter(torch.full((2,), float(step)))
    optimizer = torch.optim.Adam([weight], lr=0.1)
    return save_checkpoint(run_dir, step, {"w": weight.detach()}, {"w": optimizer}, {},
                           {"averaged_steps": 3 if average else 0},
                           average={"w": weight.detach() * 0.5} if average else None)


def test_a_checkpoint_missing_its_average_is_damaged_and_resume_falls_back(tmp_path):
    _save(tmp_path, 2, average=False)
    newest = _save(tmp_path, 4, average=True)
    assert load_checkpoint(newest).average.keys() == {"w"}
    (newest / "average.safetensors").unlink()
    with pytest.raises(DamagedFileError, match=f"{newest / 'average.safetensors'}: missing or empty, though "
                                               f".*'extra.averaged_steps' = 3"):
        load_checkpoint(newest)
    folder, loaded = resume_checkpoint(tmp_path)
    assert folder.name == "step_00000002" and loaded.step == 2 and loaded.average == {}


def test_multiview_targets_of_an_odd_height_scale_fy_by_the_height(tmp_path, monkeypatch):
    make_capture(tmp_path, views=4, lights=2, size=16)
    for png in (tmp_path / "train").glob("*.png"):  # 16 x 15 images: targets of 8 x 7 px
        Image.open(png).crop((0, 0, 16, 15)).save(png)
    transforms = tmp_path / "transforms_train.json"
    meta = json.loads(transforms.read_text())
    transforms.write_text(json.dumps({**meta, "w": 16, "h": 15}))
    cfg = make_config("diamond", overrides={"num_gaussians": 200, "batch_size": 1, "lambda_lpips": 0.0,
                                            "mv_pixels_per_pair": 16, "mv_pairs_per_step": 2, "densify": False,
                                            "device": "cpu", "mv_target_downscale": 2})
    trainer = Trainer(cfg, [ImageSource(OLATDataset(tmp_path))], None, show_progress=False)
    assert (trainer.width, trainer.height) == (16, 15)
    scene = trainer.build_scene()
    _, target, light_pos, light_rgb = trainer.draw_batch(0)
    render = scene.render(target.viewmats, target.Ks, trainer.width, trainer.height, light_pos, light_rgb)
    seen = []
    render_geometry = scene.render_geometry
    monkeypatch.setattr(scene, "render_geometry", lambda w2c, K, width, height: (
        seen.append((K, width, height)) or render_geometry(w2c, K, width, height)))
    terms = trainer.multiview_terms(scene, render, target, 0)
    assert terms and all(math.isfinite(float(v.detach())) for v in terms.values())
    K, width, height = seen[0]
    full = trainer.Ks[0]
    assert (width, height) == (8, 7)
    torch.testing.assert_close(K[0, 0], full[0] * 8 / 16)
    torch.testing.assert_close(K[0, 1], full[1] * 7 / 15)


def test_view_pairs_draw_their_sources_from_the_batch_views():
    angles = torch.arange(8, dtype=torch.float32) * 2 * math.pi / 8
    ring = torch.stack([angles.cos(), angles.sin(), torch.zeros(8)], dim=-1)
    batch = torch.tensor([2, 2, 5])
    pairs = sample_view_pairs(ring, 60, "nearest-k", 2, torch.Generator().manual_seed(0), source_views=batch)
    assert pairs.shape == (60, 2) and set(pairs[:, 0].tolist()) == {0, 1, 2}
    assert set(((pairs[:, 1] - batch[pairs[:, 0]]) % 8).tolist()) == {1, 7}  # a ring neighbour of the source
    only_five = sample_view_pairs(ring, 40, "random", 1, torch.Generator().manual_seed(1), torch.tensor([5]),
                                  source_views=torch.tensor([5, 1]))
    assert 0 < len(only_five) < 40 and set(only_five[:, 0].tolist()) == {1}  # view 5 has no target but itself
    assert set(only_five[:, 1].tolist()) == {5}
    with pytest.raises(ValueError, match="source_views"):
        sample_view_pairs(ring, 1, "random", 1, source_views=torch.tensor([8]))
