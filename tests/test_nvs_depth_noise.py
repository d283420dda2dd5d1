"""Perturbed reference depth for the warp-hint model's fine-tuning: known answers, invariants, the training stream."""

from __future__ import annotations

import pytest
import torch
from tiny_models import TINY_NVS

from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.diffusion.nvs.config import FinetuneConfig, NVSConfig
from diamond_sss.diffusion.nvs.depth_noise import box_mean_depth, dilate, erode, move_outline, perturb_depth
from diamond_sss.diffusion.nvs.train import build_training, step_batch

OBJECT = "finetune/torus_jade"


def ring(size: int = 32, outer: int = 9, inner: int = 2, depth: float = 3.0) -> torch.Tensor:
    """A square annulus of constant depth: support where ``inner < max(|x|, |y|) <= outer`` around the centre."""
    grid = torch.arange(size) - size // 2
    chebyshev = torch.maximum(grid[:, None].abs(), grid[None, :].abs())
    return (depth * ((chebyshev > inner) & (chebyshev <= outer)).float())[None, None]


def test_dilation_and_erosion_are_squares():
    support = (ring() > 0).float()
    assert int(dilate(support, 1).sum() - support.sum()) == 21 * 21 - 19 * 19 + 5 * 5 - 3 * 3
    assert int(support.sum() - erode(support, 1).sum()) == 19 * 19 - 17 * 17 + 7 * 7 - 5 * 5
    assert torch.equal(erode(dilate(support, 3), 3), (ring(inner=-1) > 0).float())  # a closing fills the 5 x 5 hole


def test_new_support_takes_the_mean_depth_of_the_old_support_around_it():
    depth = ring(depth=2.5)
    old = (depth > 0).float()
    filled = box_mean_depth(depth, old, 3)
    assert torch.allclose(filled[old.expand_as(filled) > 0], torch.tensor(2.5))
    assert torch.allclose(filled[0, 0, 16, 16], torch.tensor(2.5))  # the hole's centre, 3 pixels from the ring
    left_right = torch.cat([torch.full((1, 1, 4, 3), 1.0), torch.full((1, 1, 4, 3), 3.0)], dim=-1)
    assert torch.allclose(box_mean_depth(left_right, torch.ones_like(left_right), 1)[0, 0, 1, 2:4],
                          torch.tensor([5 / 3, 7 / 3]))


def test_a_moved_outline_keeps_the_old_depth_and_fills_the_new_pixels_from_it():
    depth = ring(depth=2.5)
    grown, shrunk = move_outline(depth, 2), move_outline(depth, -1)
    assert torch.equal((grown > 0).float(), dilate((depth > 0).float(), 2))
    assert torch.allclose(grown[grown > 0], torch.tensor(2.5))
    assert torch.equal(shrunk, depth * erode((depth > 0).float(), 1))
    assert torch.equal(move_outline(depth, 0), depth)


def test_share_zero_is_the_identity_and_draws_nothing():
    depth = ring()
    generator = torch.Generator().manual_seed(0)
    state = generator.get_state()
    assert perturb_depth(depth, generator, 0.0, 0.2, 2) is depth
    assert torch.equal(generator.get_state(), state)


def test_perturbed_maps_repeat_under_a_seed_and_change_only_by_a_smooth_relative_error_without_edge_moves():
    depth = ring().expand(16, 1, 32, 32).clone()
    outs = [perturb_depth(depth, torch.Generator().manual_seed(5), 1.0, 0.2, 0) for _ in range(2)]
    assert torch.equal(outs[0], outs[1])
    out = outs[0]
    assert torch.equal(out > 0, depth > 0)
    relative = (out - depth)[depth > 0] / depth[depth > 0]
    assert 0 < float(relative.abs().max()) and float(relative.std()) < 0.2 * 3
    assert not torch.equal(perturb_depth(depth, torch.Generator().manual_seed(6), 1.0, 0.2, 0), out)
    half = perturb_depth(depth, torch.Generator().manual_seed(5), 0.5, 0.2, 0)
    kept = [torch.equal(half[b], depth[b]) for b in range(16)]
    assert any(kept) and not all(kept)  # a share of the maps left as they were


def test_the_relative_error_is_smooth_and_the_outline_moves_both_ways():
    depth = torch.full((32, 1, 32, 32), 2.0)
    depth[..., :4, :] = 0
    out = perturb_depth(depth, torch.Generator().manual_seed(1), 1.0, 0.3, 2, grid=4)
    rows = (out > 0).float().sum(dim=(1, 2, 3)) / 32  # foreground rows per map: 28 +- up to 2
    assert set(rows.tolist()) <= {26.0, 27.0, 28.0, 29.0, 30.0} and len(set(rows.tolist())) > 1
    full = perturb_depth(torch.full((32, 1, 33, 33), 2.0), torch.Generator().manual_seed(2), 1.0, 0.3, 0, grid=4)
    steps = torch.maximum((full[..., 1:] - full[..., :-1]).abs().amax(dim=(1, 2, 3)),
                          (full[..., 1:, :] - full[..., :-1, :]).abs().amax(dim=(1, 2, 3)))
    spread = full.amax(dim=(1, 2, 3)) - full.amin(dim=(1, 2, 3))
    assert float(spread.min()) > 0
    # bilinear between lattice knots 8 pixels apart, on pixels, whose values lie in the map's range: no jumps
    assert (steps <= spread / 8 + 1e-5).all()


def test_settings_are_checked():
    with pytest.raises(ValueError, match="share must be in"):
        perturb_depth(ring(), torch.Generator(), 1.5, 0.1, 1)
    with pytest.raises(ValueError, match="relative and edge_px must be finite"):
        perturb_depth(ring(), torch.Generator(), 1.0, float("nan"), 1)
    with pytest.raises(ValueError, match=r"\[B,1,H,W\]"):
        perturb_depth(ring()[0], torch.Generator(), 1.0, 0.1, 1)
    with pytest.raises(ValueError, match="depth_noise_share must be in"):
        FinetuneConfig(depth_noise_share=-0.1)
    with pytest.raises(ValueError, match="depth_noise_edge_px"):
        FinetuneConfig(depth_noise_edge_px=-1)
    with pytest.raises(ValueError, match="warp_hint=True"):
        FinetuneConfig(depth_noise_share=0.5, model=NVSConfig(warp_hint=False))


def test_a_training_batch_with_depth_noise_is_a_pure_function_of_seed_and_step():
    data = [embedded_dataset(OBJECT)]
    noisy = FinetuneConfig(objects_per_batch=2, views_per_object=2, depth_noise_share=1.0, depth_noise_relative=0.1,
                           depth_noise_edge_px=1, model=NVSConfig(**TINY_NVS))
    clean = FinetuneConfig(objects_per_batch=2, views_per_object=2, model=NVSConfig(**TINY_NVS))
    state = build_training(data, noisy)
    first, again = step_batch(state, noisy, 3), step_batch(state, noisy, 3)
    truth = step_batch(state, clean, 3)
    assert torch.equal(first.reference_depth, again.reference_depth)
    assert torch.equal(first.targets, truth.targets)  # the same draw of views: the noise comes after it
    assert not torch.equal(first.reference_depth, truth.reference_depth)
    assert not torch.equal(step_batch(state, noisy, 4).reference_depth, first.reference_depth)
