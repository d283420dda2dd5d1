"""Tests of diamond_sss.losses.multiview on constructed scenes with known answers."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture
from diamond_sss.data.conventions import (
    camera_centers,
    intrinsics_from_fov,
    look_at_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    pixel_grid,
    project_points,
    unproject_pixels,
)
from diamond_sss.losses import (
    MultiViewConfig,
    multiview_losses,
    multiview_losses_batched,
    sample_foreground_pixels,
    sample_view_pairs,
)
from diamond_sss.rendering import rasterize
from diamond_sss.training import trainer as trainer_module
from diamond_sss.training.overrides import make_config
from diamond_sss.training.trainer import ImageSource, Trainer

SIZE = 32
FOV = math.radians(60.0)
NEAR, FAR = 1.0, 5.0
SPAN = FAR - NEAR


def camera(eye, target, size: int = SIZE) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV ``w2c`` and ``K`` (float64) of a camera at ``eye`` looking at ``target``."""
    c2w = look_at_opengl_c2w(
        torch.tensor(eye, dtype=torch.float64), torch.tensor(target, dtype=torch.float64)
    )
    return opengl_c2w_to_opencv_w2c(c2w), intrinsics_from_fov(FOV, size, size).to(torch.float64)


def ground_plane_depth(w2c: torch.Tensor, K: torch.Tensor, size: int = SIZE) -> torch.Tensor:
    """Analytic camera-space depth of the plane ``z = 0``: ``D = -C_z / w_z``, ``w`` the ray at unit depth."""
    uv = pixel_grid(size, size).to(torch.float64).reshape(-1, 2)
    center = camera_centers(w2c)
    rays = unproject_pixels(uv, torch.ones(uv.shape[0], dtype=torch.float64), w2c, K) - center
    return (-center[2] / rays[:, 2]).reshape(size, size)


def two(x: torch.Tensor) -> torch.Tensor:
    """The same view twice, ``[2, ...]``."""
    return torch.stack([x, x])


def all_pixels(size: int = SIZE) -> torch.Tensor:
    return pixel_grid(size, size).to(torch.float64).reshape(-1, 2)


def ones(size: int = SIZE) -> torch.Tensor:
    return torch.ones(size, size, dtype=torch.float64)


def run(src, tgt, src_depth, tgt_depth, cfg=None, uv=None, src_alpha=None, tgt_alpha=None, sil=None):
    """Multi-view losses of one pair; alpha, silhouette and pixels default to all ones / every pixel."""
    (src_w2c, src_K), (tgt_w2c, tgt_K) = src, tgt
    src_ones, tgt_ones = torch.ones_like(src_depth.detach()), torch.ones_like(tgt_depth.detach())
    return multiview_losses(
        src_depth,
        src_ones if src_alpha is None else src_alpha,
        all_pixels(src_depth.shape[0]).to(src_depth.device) if uv is None else uv,
        src_w2c,
        src_K,
        tgt_depth,
        tgt_ones if tgt_alpha is None else tgt_alpha,
        tgt_ones if sil is None else sil,
        tgt_w2c,
        tgt_K,
        NEAR,
        FAR,
        cfg or MultiViewConfig(),
    )


# ----------------------------------------------------------------------------- known answers on a plane


def test_consistent_tilted_views_give_zero_loss():
    src = camera((0.3, -0.2, 3.0), (0.0, 0.0, 0.0))
    tgt = camera((1.0, 0.6, 2.8), (0.1, 0.0, 0.0))
    terms = run(src, tgt, ground_plane_depth(*src), ground_plane_depth(*tgt))
    assert terms.n_silhouette > 0.8 * SIZE * SIZE and terms.n_depth == terms.n_silhouette
    assert terms.silhouette.item() == pytest.approx(0.0, abs=1e-12)
    # Bilinear interpolation of the (projective, not bilinear) plane depth is the only error.
    assert terms.depth.item() < 1e-4


@pytest.mark.parametrize("charbonnier_eps", [None, 0.01])
def test_depth_offset_gives_closed_form_normalised_error(charbonnier_eps):
    # Two fronto-parallel cameras translated along the plane: depth is 2 everywhere in both views,
    # and a source offset delta moves X to depth 2 + delta in the target as well.
    src = camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))
    tgt = camera((0.3, 0.0, 2.0), (0.3, 0.0, 0.0))
    cfg = MultiViewConfig(occlusion_tol=1.0, charbonnier_eps=charbonnier_eps)
    for delta in (-0.4, -0.1, 0.0, 0.1, 0.3):
        terms = run(src, tgt, 2.0 * ones() + delta, 2.0 * ones(), cfg)
        d = abs(delta) / SPAN
        expected = d if charbonnier_eps is None else math.sqrt(d * d + charbonnier_eps**2) - charbonnier_eps
        assert terms.n_depth > 0
        assert terms.depth.item() == pytest.approx(expected, abs=1e-9)


def test_depth_loss_grows_monotonically_with_offset_on_tilted_views():
    src = camera((0.3, -0.2, 3.0), (0.0, 0.0, 0.0))
    tgt = camera((1.0, 0.6, 2.8), (0.1, 0.0, 0.0))
    cfg = MultiViewConfig(occlusion_tol=1.0)
    base_src, base_tgt = ground_plane_depth(*src), ground_plane_depth(*tgt)
    for sign in (-1.0, 1.0):
        losses = [
            run(src, tgt, base_src + sign * delta, base_tgt, cfg).depth.item()
            for delta in (0.0, 0.05, 0.1, 0.2)
        ]
        assert all(a < b for a, b in itertools.pairwise(losses)), losses


# ----------------------------------------------------------------------------- filters


def test_each_filter_removes_exactly_the_constructed_correspondences():
    size = 16
    view = camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), size)  # target == source: x' == x exactly
    src_depth = 2.0 * ones(size)
    src_alpha = ones(size)
    src_depth[0, 0] = 0.0
    src_depth[0, 1] = float("nan")
    src_depth[0, 2] = float("inf")
    src_alpha[0, 3] = 0.1
    tgt_depth = 2.0 * ones(size)
    tgt_alpha = ones(size)
    tgt_depth[5, 5] = float("nan")
    tgt_depth[5, 7] = -1.0
    tgt_alpha[5, 9] = 0.0
    sil = ones(size)
    sil[8, 8] = 0.2  # outside the silhouette (tolerance 0.5): dropped from the depth term only
    tgt_depth[10, 10] = 2.0 - 0.5  # z_ij behind D_j by 0.125 > occlusion_tol = 0.02: occluded
    tgt_depth[10, 12] = 2.0 - 0.04  # behind by 0.01 <= tol: kept, residual 0.01
    tgt_depth[12, 12] = 2.0 + 0.5  # in front (free-space violation): kept, residual 0.125
    src_depth.requires_grad_(True)
    tgt_depth.requires_grad_(True)
    cfg = MultiViewConfig(sil_threshold=0.5, occlusion_tol=0.02, alpha_threshold=0.5, sil_tolerance=0.5)
    terms = run(view, view, src_depth, tgt_depth, cfg, src_alpha=src_alpha, tgt_alpha=tgt_alpha, sil=sil)
    n_valid_source = size * size - 4
    assert terms.n_silhouette.item() == n_valid_source
    assert terms.silhouette.item() == pytest.approx((0.5 - 0.2) / 0.5 / n_valid_source, abs=1e-9)  # tau = 0.5
    assert terms.n_depth.item() == n_valid_source - 3 - 1 - 1
    assert terms.depth.item() == pytest.approx((0.01 + 0.125) / terms.n_depth.item(), abs=1e-9)
    # Without the occlusion filter the invalid target depths are still dropped, the occluded point is not.
    no_occlusion = MultiViewConfig(sil_threshold=0.5, occlusion_tol=1.0, alpha_threshold=0.5, sil_tolerance=0.5)
    kept = run(
        view, view, src_depth, tgt_depth, no_occlusion, src_alpha=src_alpha, tgt_alpha=tgt_alpha, sil=sil
    )
    assert kept.n_depth.item() == n_valid_source - 3 - 1
    assert kept.depth.item() == pytest.approx((0.125 + 0.01 + 0.125) / kept.n_depth.item(), abs=1e-9)
    (terms.silhouette + terms.depth).backward()
    assert torch.isfinite(src_depth.grad).all() and torch.isfinite(tgt_depth.grad).all()
    assert src_depth.grad[0, :4].abs().sum() == 0 and tgt_depth.grad[10, 10] == 0
    # The depth term reaches the target depth map (D_j is not detached).
    assert tgt_depth.grad[10, 12] != 0 and tgt_depth.grad[12, 12] != 0


def test_silhouette_residual_is_a_hinge_at_the_tolerance():
    size = 4
    view = camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), size)  # target == source: x' == x exactly
    sil = torch.tensor([0.0, 0.25, 0.5, 0.8], dtype=torch.float64).repeat(size, 1)  # by column
    for tau, per_column in ((0.5, [1.0, 0.5, 0.0, 0.0]), (1.0, [1.0, 0.75, 0.5, 0.2])):
        terms = run(view, view, 2.0 * ones(size), 2.0 * ones(size), MultiViewConfig(sil_tolerance=tau), sil=sil)
        assert terms.n_silhouette.item() == size * size
        assert terms.silhouette.item() == pytest.approx(sum(per_column) / size, abs=1e-12)
    with pytest.raises(ValueError, match="sil_tolerance"):
        MultiViewConfig(sil_tolerance=0.0)
    with pytest.raises(ValueError, match="depth_tolerance"):
        MultiViewConfig(depth_tolerance=-0.1)


def test_depth_tolerance_shrinks_each_residual_by_delta():
    # Fronto-parallel views translated along a plane: the residual is |delta_z| / SPAN everywhere.
    src = camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))
    tgt = camera((0.3, 0.0, 2.0), (0.3, 0.0, 0.0))
    for offset, tolerance, expected in ((0.4, 0.05, 0.1 - 0.05), (-0.4, 0.05, 0.1 - 0.05), (0.1, 0.05, 0.0)):
        depth = (2.0 * ones() + offset).requires_grad_(True)
        terms = run(src, tgt, depth, 2.0 * ones(), MultiViewConfig(occlusion_tol=1.0, depth_tolerance=tolerance))
        assert terms.depth.item() == pytest.approx(expected, abs=1e-9)
        terms.depth.backward()
        assert (depth.grad.abs().sum() > 0) == (expected > 0)


def test_targets_without_a_silhouette_give_depth_but_no_silhouette_correspondences():
    src = camera((0.3, -0.2, 3.0), (0.0, 0.0, 0.0))
    tgt = camera((1.0, 0.6, 2.8), (0.1, 0.0, 0.0))
    src_depth, tgt_depth = ground_plane_depth(*src) + 0.1, ground_plane_depth(*tgt)
    sil = torch.zeros(SIZE, SIZE, dtype=torch.float64)  # every point lands outside
    cfg = MultiViewConfig(occlusion_tol=1.0, sil_threshold=0.0, depth_tolerance=0.0)
    single = run(src, tgt, src_depth, tgt_depth, cfg, sil=sil)
    assert single.silhouette.item() == 1.0 and single.n_depth > 0
    uv = all_pixels()
    batched = multiview_losses_batched(
        two(src_depth), two(ones()), two(uv), two(src[0]), two(src[1]), two(tgt_depth), two(ones()), two(sil),
        two(tgt[0]), two(tgt[1]), NEAR, FAR, cfg, tgt_silhouette_valid=torch.tensor([True, False]),
    )
    assert batched.n_silhouette == single.n_silhouette and batched.silhouette.item() == 1.0
    assert batched.n_depth == 2 * single.n_depth
    assert batched.depth.item() == pytest.approx(single.depth.item(), rel=1e-12)
    with pytest.raises(ValueError, match="tgt_silhouette_valid"):
        multiview_losses_batched(
            two(src_depth), two(ones()), two(uv), two(src[0]), two(src[1]), two(tgt_depth), two(ones()),
            two(sil), two(tgt[0]), two(tgt[1]), NEAR, FAR, cfg, tgt_silhouette_valid=torch.tensor([True]),
        )


def test_points_outside_the_target_image_are_dropped():
    src = camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))
    tgt = camera((1.5, 0.0, 2.0), (1.5, 0.0, 0.0))
    fx = float(src[1][0, 0])
    # X = 2 (u - 16) / fx in the source; u' = fx (X - 1.5) / 2 + 16 must lie in [0, 32).
    columns = torch.arange(SIZE, dtype=torch.float64) + 0.5
    u_target = fx * (2.0 * (columns - SIZE / 2) / fx - 1.5) / 2.0 + SIZE / 2
    inside_columns = int(((u_target >= 0) & (u_target < SIZE)).sum())
    assert 0 < inside_columns < SIZE
    terms = run(src, tgt, 2.0 * ones(), 2.0 * ones())
    assert terms.n_silhouette.item() == inside_columns * SIZE
    assert terms.n_depth.item() == inside_columns * SIZE
    assert terms.silhouette.item() == 0.0 and terms.depth.item() == pytest.approx(0.0, abs=1e-12)


def test_points_at_or_before_the_near_plane_are_dropped():
    view = camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))
    src_depth = 2.0 * ones()
    src_depth[:4] = 0.8  # in front of near = 1
    terms = run(view, view, src_depth, 2.0 * ones())
    assert terms.n_silhouette.item() == (SIZE - 4) * SIZE
    assert terms.n_depth.item() == (SIZE - 4) * SIZE


# ----------------------------------------------------------------------------- normalisation and edge cases


def offset_plane_pair():
    """Two cameras over the ground plane with the source's depth 0.1 too far, a silhouette ramp and a square
    foreground mask: ``(src, tgt, src_depth, tgt_depth, sil, mask)``."""
    src = camera((0.3, -0.2, 3.0), (0.0, 0.0, 0.0))
    tgt = camera((1.0, 0.6, 2.8), (0.1, 0.0, 0.0))
    sil = torch.linspace(0.0, 1.0, SIZE, dtype=torch.float64).expand(SIZE, SIZE).contiguous()
    mask = torch.zeros(SIZE, SIZE)
    mask[8:24, 8:24] = 1.0
    return src, tgt, ground_plane_depth(*src) + 0.1, ground_plane_depth(*tgt), sil, mask


def test_duplicated_correspondences_leave_the_loss_unchanged():
    src, tgt, src_depth, tgt_depth, sil, mask = offset_plane_pair()
    uv = sample_foreground_pixels(mask, 50, torch.Generator().manual_seed(0)).to(torch.float64)
    cfg = MultiViewConfig(occlusion_tol=1.0, sil_threshold=0.3)
    once = run(src, tgt, src_depth, tgt_depth, cfg, uv=uv, sil=sil)
    twice = run(src, tgt, src_depth, tgt_depth, cfg, uv=torch.cat([uv, uv]), sil=sil)
    assert once.silhouette > 0 and once.depth > 0
    assert twice.n_silhouette == 2 * once.n_silhouette and twice.n_depth == 2 * once.n_depth
    assert twice.silhouette.item() == pytest.approx(once.silhouette.item(), rel=1e-12)
    assert twice.depth.item() == pytest.approx(once.depth.item(), rel=1e-12)
    # The batched form normalises by the counts over all pairs, and padding entries are ignored.
    padded_uv = torch.stack([uv, torch.cat([uv[:30], torch.full_like(uv[30:], float("nan"))])])
    uv_valid = torch.ones(2, uv.shape[0], dtype=torch.bool)
    uv_valid[1, 30:] = False
    batched = multiview_losses_batched(
        two(src_depth),
        two(ones()),
        padded_uv,
        two(src[0]),
        two(src[1]),
        two(tgt_depth),
        two(ones()),
        two(sil),
        two(tgt[0]),
        two(tgt[1]),
        NEAR,
        FAR,
        cfg,
        src_uv_valid=uv_valid,
    )
    partial = run(src, tgt, src_depth, tgt_depth, cfg, uv=uv[:30], sil=sil)
    expected_n = once.n_silhouette + partial.n_silhouette
    assert batched.n_silhouette == expected_n
    expected = (once.silhouette * once.n_silhouette + partial.silhouette * partial.n_silhouette) / expected_n
    assert batched.silhouette.item() == pytest.approx(expected.item(), rel=1e-10)


def test_empty_mask_gives_exact_zero_and_backward_works():
    view = camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))
    uv = sample_foreground_pixels(torch.zeros(SIZE, SIZE), 64, torch.Generator().manual_seed(0))
    assert uv.shape == (0, 2)
    src_depth = (2.0 * ones()).requires_grad_(True)
    tgt_depth = (2.0 * ones()).requires_grad_(True)
    terms = run(view, view, src_depth, tgt_depth, uv=uv.to(torch.float64))
    total = terms.silhouette + terms.depth
    assert total.item() == 0.0 and not torch.isnan(total)
    assert terms.n_silhouette.item() == 0 and terms.n_depth.item() == 0
    total.backward()
    assert torch.equal(src_depth.grad, torch.zeros_like(src_depth))
    # Nothing valid at all (transparent source) is the same.
    src_depth.grad = None
    terms = run(view, view, src_depth, tgt_depth, src_alpha=torch.zeros(SIZE, SIZE, dtype=torch.float64))
    (terms.silhouette + terms.depth).backward()
    assert terms.silhouette.item() == 0.0 and terms.depth.item() == 0.0
    assert torch.isfinite(src_depth.grad).all()


# ----------------------------------------------------------------------------- gradients


def test_silhouette_gradient_pulls_reprojection_back_inside():
    src = camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))
    tgt = camera((2.0, 0.0, 2.0), (0.0, 0.0, 0.0))
    # Target silhouette: a soft disc around the projection of the origin.
    grid = pixel_grid(SIZE, SIZE).to(torch.float64)
    centre, _ = project_points(torch.zeros(1, 3, dtype=torch.float64), *tgt)
    sil = torch.exp(-((grid - centre[0]) ** 2).sum(-1) / (2 * 4.0**2))
    # The object surface is the plane z = 0 (true source depth 2); the rendered depth is 0.6 too far,
    # so X lands 0.6 below the plane and reprojects off the disc.
    uv = torch.tensor([[15.5, 15.5], [16.5, 16.5], [17.5, 15.5]], dtype=torch.float64)
    src_depth = (2.6 * ones()).requires_grad_(True)
    cfg = MultiViewConfig(sil_tolerance=1.0)  # the plain 1 - S
    terms = run(src, tgt, src_depth, 2.0 * ones(), cfg, uv=uv, sil=sil)
    assert terms.n_silhouette.item() == 3 and terms.silhouette.item() > 0.1
    terms.silhouette.backward()
    rows, cols = (uv[:, 1] - 0.5).long(), (uv[:, 0] - 0.5).long()
    assert (src_depth.grad[rows, cols] > 0).all()  # less depth -> closer to the disc
    with torch.no_grad():
        stepped = src_depth - 0.5 * src_depth.grad / src_depth.grad.abs().max()
    after = run(src, tgt, stepped, 2.0 * ones(), cfg, uv=uv, sil=sil)
    assert after.silhouette.item() < terms.silhouette.item()


def test_gradcheck_both_terms_wrt_source_and_target_depth():
    size = 12
    src = camera((0.3, -0.2, 3.0), (0.0, 0.0, 0.0), size)
    tgt = camera((1.0, 0.6, 2.8), (0.1, 0.0, 0.0), size)
    gen = torch.Generator().manual_seed(1)
    src_depth = ground_plane_depth(*src, size=size) + 0.05 * torch.rand(
        size, size, generator=gen, dtype=torch.float64
    )
    tgt_depth = ground_plane_depth(*tgt, size=size) + 0.05 * torch.rand(
        size, size, generator=gen, dtype=torch.float64
    )
    grid = pixel_grid(size, size).to(torch.float64)
    sil = torch.sigmoid(0.4 * (grid[..., 0] - 3.0))
    uv = all_pixels(size)[::5]
    cfg = MultiViewConfig(occlusion_tol=1.0, sil_threshold=0.0, charbonnier_eps=1e-3)

    def objective(d_src, d_tgt):
        terms = run(src, tgt, d_src, d_tgt, cfg, uv=uv, sil=sil)
        return terms.silhouette + terms.depth

    inputs = (src_depth.requires_grad_(True), tgt_depth.requires_grad_(True))
    assert torch.autograd.gradcheck(objective, inputs, atol=1e-6)
    objective(*inputs).backward()
    assert src_depth.grad.abs().sum() > 0 and tgt_depth.grad.abs().sum() > 0


# ----------------------------------------------------------------------------- sampling


def ring_centres(num: int = 8) -> torch.Tensor:
    angles = torch.arange(num, dtype=torch.float64) * 2 * math.pi / num
    return torch.stack([torch.cos(angles), torch.sin(angles), torch.zeros(num, dtype=torch.float64)], dim=-1)


def test_sample_view_pairs_nearest_k_and_random():
    centres = ring_centres(8)
    pairs = sample_view_pairs(centres, 200, "nearest-k", 2, torch.Generator().manual_seed(0))
    assert pairs.shape == (200, 2) and pairs.dtype == torch.int64
    step = (pairs[:, 1] - pairs[:, 0]) % 8
    assert set(step.tolist()) == {1, 7}  # the two ring neighbours, never the source itself
    again = sample_view_pairs(centres, 200, "nearest-k", 2, torch.Generator().manual_seed(0))
    assert torch.equal(pairs, again)
    random_pairs = sample_view_pairs(centres, 400, "random", 2, torch.Generator().manual_seed(1))
    assert (random_pairs[:, 0] != random_pairs[:, 1]).all()
    assert len(set(((random_pairs[:, 1] - random_pairs[:, 0]) % 8).tolist())) == 7
    restricted = sample_view_pairs(
        centres, 100, "random", 1, torch.Generator().manual_seed(2), torch.tensor([2, 5])
    )
    assert set(restricted[:, 1].tolist()) <= {2, 5}
    assert (restricted[:, 0] != restricted[:, 1]).all()
    assert sample_view_pairs(centres[:1], 3, "random", 1, torch.Generator().manual_seed(0)).shape == (0, 2)
    with pytest.raises(ValueError, match="mode"):
        sample_view_pairs(centres, 1, "farthest", 1)


def test_sample_foreground_pixels():
    mask = torch.zeros(10, 12)
    mask[2:5, 3:7] = 1.0
    uv = sample_foreground_pixels(mask, 5, torch.Generator().manual_seed(0))
    assert uv.shape == (5, 2)
    assert torch.equal(uv - uv.floor(), torch.full_like(uv, 0.5))
    rows, cols = (uv[:, 1] - 0.5).long(), (uv[:, 0] - 0.5).long()
    assert (mask[rows, cols] == 1).all()
    assert len({(r, c) for r, c in zip(rows.tolist(), cols.tolist())}) == 5
    assert torch.equal(uv, sample_foreground_pixels(mask, 5, torch.Generator().manual_seed(0)))
    assert sample_foreground_pixels(mask, 100).shape == (12, 2)


def test_config_validation():
    with pytest.raises(ValueError, match="target_mode"):
        MultiViewConfig(target_mode="nearest")
    with pytest.raises(ValueError, match="charbonnier_eps"):
        MultiViewConfig(charbonnier_eps=0.0)
    view = camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="far > near"):
        multiview_losses(
            ones(), ones(), all_pixels(), *view, ones(), ones(), ones(), *view, 2.0, 1.0, MultiViewConfig()
        )


# ----------------------------------------------------------------------------- with the rasterizer


def test_gaussian_outside_target_silhouette_is_pulled_back_inside():
    src = tuple(x.to(torch.float32) for x in camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0)))
    tgt = tuple(x.to(torch.float32) for x in camera((3.0, 0.0, 0.0), (0.0, 0.0, 0.0)))
    # Target silhouette: a soft disc around the projection of the origin (where the object is).
    grid = pixel_grid(SIZE, SIZE)
    centre, _ = project_points(torch.zeros(1, 3), *tgt)
    sil = torch.exp(-((grid - centre[0]) ** 2).sum(-1) / (2 * 5.0**2))
    # One Gaussian on the source's optical axis, 0.8 behind the origin: outside the disc in the target view.
    mean = torch.tensor([[0.0, 0.0, -0.8]], requires_grad=True)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    scales = torch.full((1, 3), 0.3)
    opacities = torch.tensor([0.99])
    optimizer = torch.optim.SGD([mean], lr=0.3)

    def silhouette_at_projection() -> float:
        uv, _ = project_points(mean.detach(), *tgt)
        col, row = int(uv[0, 0]), int(uv[0, 1])
        return float(sil[row, col]) if 0 <= row < SIZE and 0 <= col < SIZE else 0.0

    before = silhouette_at_projection()
    losses = []
    for _ in range(6):
        out = rasterize(
            mean,
            quats,
            scales,
            opacities,
            torch.ones(1, 1),
            src[0][None],
            src[1][None],
            SIZE,
            SIZE,
            backend="cpu",
        )
        depth, alpha = out.depth[0, ..., 0], out.alpha[0, ..., 0]
        uv = sample_foreground_pixels(alpha.detach(), 64, torch.Generator().manual_seed(0))
        terms = multiview_losses(
            depth,
            alpha,
            uv,
            *src,
            torch.full((SIZE, SIZE), 3.0),
            ones().float(),
            sil,
            *tgt,
            0.5,
            6.0,
            MultiViewConfig(),
        )
        optimizer.zero_grad()
        terms.silhouette.backward()
        optimizer.step()
        losses.append(terms.silhouette.item())
    assert before < 0.5 and silhouette_at_projection() > 0.5  # outside, then inside (tolerance 0.5)
    assert losses[-1] < 0.1 * losses[0]


def splat_camera(eye, size: int = SIZE, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """A 40-degree camera at ``eye`` looking at the origin, in ``dtype``."""
    c2w = look_at_opengl_c2w(torch.tensor(eye, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    return opengl_c2w_to_opencv_w2c(c2w).to(dtype), intrinsics_from_fov(math.radians(40.0), size, size).to(dtype)


def splat_depth(means, scales, opacities, view, size: int = SIZE) -> tuple[torch.Tensor, torch.Tensor]:
    """Expected depth and alpha ``[H,W]`` of isotropic-axis Gaussians rendered by the CPU rasterizer."""
    quats = torch.zeros(means.shape[0], 4, dtype=means.dtype)
    quats[:, 0] = 1.0
    ones_feature = torch.ones(means.shape[0], 1, dtype=means.dtype)
    out = rasterize(means, quats, scales, opacities, ones_feature, view[0][None], view[1][None], size, size,
                    backend="cpu")
    return out.depth[0, ..., 0], out.alpha[0, ..., 0]


def sphere_shell(count: int, radius: float) -> torch.Tensor:
    """Fibonacci points on a sphere about the origin ``[count,3]``."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    polar, azimuth = torch.acos(1 - 2 * i / count), math.pi * (1 + 5**0.5) * i
    return radius * torch.stack([azimuth.cos() * polar.sin(), azimuth.sin() * polar.sin(), polar.cos()], dim=-1)


SPLAT_SRC = (0.0, 0.0, 3.0)
SPLAT_TGT = (3.0 * math.sin(math.radians(35.0)), 0.0, 3.0 * math.cos(math.radians(35.0)))


def splat_terms(means, scales, opacities, cfg, size: int = SIZE, near: float = 1.0, far: float = 5.0):
    """Both terms between the two splat cameras, every source pixel with alpha > 0.5; the target silhouette is
    the target render's own alpha > 0.5 (the true configuration's mask when the scene is the truth)."""
    src, tgt = splat_camera(SPLAT_SRC, size, means.dtype), splat_camera(SPLAT_TGT, size, means.dtype)
    src_depth, src_alpha = splat_depth(means, scales, opacities, src, size)
    tgt_depth, tgt_alpha = splat_depth(means, scales, opacities, tgt, size)
    uv = sample_foreground_pixels((src_alpha.detach() > 0.5).float(), size * size).to(means.dtype)
    sil = (tgt_alpha.detach() > 0.5).to(means.dtype)
    return multiview_losses(src_depth, src_alpha, uv, *src, tgt_depth, tgt_alpha, sil, *tgt, near, far, cfg)


def test_a_correct_tilted_plane_of_splats_costs_nothing_within_the_depth_tolerance():
    # The plane z = 0 tiled by flat splats, seen head-on (source) and 35 degrees off its normal (target). The
    # expected depth counts each splat at its centre and the nearer centres win, so the tilted view's depth is
    # about 0.013 (normalised) too near everywhere: a correct scene that the untolerant term would distort.
    axis = torch.linspace(-1.2, 1.2, 41)
    x, y = torch.meshgrid(axis, axis, indexing="ij")
    means = torch.stack([x.flatten(), y.flatten(), torch.zeros(x.numel())], dim=-1)
    scales = torch.tensor([0.05, 0.05, 0.002]).expand(means.shape[0], 3).contiguous()
    opacities = torch.full((means.shape[0],), 0.99)
    strict = splat_terms(means, scales, opacities, MultiViewConfig(depth_tolerance=0.0))
    assert strict.n_depth > 500 and 0.008 < strict.depth.item() < 0.02
    tolerant = splat_terms(means, scales, opacities, MultiViewConfig(depth_tolerance=0.02, sil_tolerance=0.5))
    assert tolerant.n_depth == strict.n_depth
    assert tolerant.depth.item() == 0.0 and tolerant.silhouette.item() == 0.0


def test_depth_gradient_moves_a_displaced_splat_back_to_the_sphere():
    means = sphere_shell(300, 0.6).float()
    scales, opacities = torch.full((300, 3), 0.07), torch.full((300,), 0.95)
    front = int(means[:, 2].argmax())  # on the source's optical axis, facing it
    gradients = {}
    for delta in (0.0, 0.2, 0.3):  # displacement towards the source camera, along its ray
        moved = means.clone()
        moved[front, 2] += delta
        moved.requires_grad_(True)
        splat_terms(moved, scales, opacities, MultiViewConfig(depth_tolerance=0.02), near=1.5, far=4.5).depth.backward()
        gradients[delta] = moved.grad[front, 2].item()
    assert abs(gradients[0.0]) < 1e-4  # the true configuration: nothing to correct
    assert gradients[0.3] > gradients[0.2] > 1e-3  # descent lowers z: back onto the surface, harder when farther
    # Without the tolerance the true shell is pushed off: its ED inconsistency at the limbs is not zero.
    moved = means.clone().requires_grad_(True)
    splat_terms(moved, scales, opacities, MultiViewConfig(depth_tolerance=0.0), near=1.5, far=4.5).depth.backward()
    assert moved.grad[front, 2].item() < -1e-3


def test_gradients_through_the_rasterizer_match_finite_differences():
    size = 12
    means = sphere_shell(40, 0.6).requires_grad_(True)
    scales = torch.full((40, 3), 0.12, dtype=torch.float64)
    opacities = torch.full((40,), 0.9, dtype=torch.float64)
    src, tgt = splat_camera(SPLAT_SRC, size, torch.float64), splat_camera(SPLAT_TGT, size, torch.float64)
    uv = sample_foreground_pixels((splat_depth(means.detach(), scales, opacities, src, size)[1] > 0.5).float(), 30,
                                  torch.Generator().manual_seed(0)).to(torch.float64)
    sil = torch.sigmoid(0.8 * (pixel_grid(size, size)[..., 0].to(torch.float64) - 4.0))
    cfg = MultiViewConfig(charbonnier_eps=1e-2, occlusion_tol=1.0, depth_tolerance=0.0, sil_tolerance=1.0)

    def objective(points):
        src_depth, src_alpha = splat_depth(points, scales, opacities, src, size)
        tgt_depth, tgt_alpha = splat_depth(points, scales, opacities, tgt, size)
        terms = multiview_losses(src_depth, src_alpha, uv, *src, tgt_depth, tgt_alpha, sil, *tgt, 1.5, 4.5, cfg)
        assert terms.n_silhouette > 10 and terms.n_depth > 10
        return terms.silhouette + terms.depth

    assert torch.autograd.gradcheck(objective, (means,), atol=1e-6)


def test_trainer_terms_start_late_and_unobserved_targets_have_no_silhouette(tmp_path, monkeypatch):
    make_capture(tmp_path, views=4, lights=2, size=16)
    dataset = OLATDataset(tmp_path)
    observed = [i for i, obs in enumerate(dataset.observations) if obs.view in (0, 1)]  # views 2, 3: no image
    cfg = make_config("diamond", overrides={
        "iterations": 10, "num_gaussians": 200, "batch_size": 1, "lambda_lpips": 0.0, "densify": False,
        "device": "cpu", "mv_pixels_per_pair": 16, "mv_pairs_per_step": 8, "mv_target_mode": "random",
        "mv_start_fraction": 0.5, "mv_include_unobserved_views": True})
    trainer = Trainer(cfg, [ImageSource(dataset.subset(observed))], None, show_progress=False)
    scene = trainer.build_scene()
    _, target, light_pos, light_rgb = trainer.draw_batch(0)
    render = scene.render(target.viewmats, target.Ks, trainer.width, trainer.height, light_pos, light_rgb)
    assert trainer.multiview_terms(scene, render, target, 4) == {}  # before 0.5 x 10 steps
    calls = []
    losses = trainer_module.multiview_losses_batched
    monkeypatch.setattr(trainer, "_multiview_losses",
                        lambda *args, **kwargs: calls.append((args, kwargs)) or losses(*args, **kwargs))
    terms = trainer.multiview_terms(scene, render, target, 5)
    assert set(terms) == {"mv_silhouette", "mv_depth"}
    (args, kwargs), = calls
    target_views = [int((trainer.viewmats - w2c).abs().sum((-2, -1)).argmin()) for w2c in args[8]]
    assert {0, 1} & set(target_views) and {2, 3} & set(target_views)
    assert kwargs["tgt_silhouette_valid"].tolist() == [view in (0, 1) for view in target_views]
    with pytest.raises(ValueError, match=r"'multiview.start_fraction' must be in \[0, 1\), got 1.0"):
        make_config("diamond", overrides={"mv_start_fraction": 1.0})  # when the config is made, not at a step


@pytest.mark.parametrize("term", ["mv_silhouette", "mv_depth"])
def test_centres_source_gradient_holds_the_blending_weights(tmp_path, term):
    """``mv_source_gradient=centres``: the same loss values (to float rounding); the terms' gradient through the source depth reaches the
    Gaussian centres (as with ``blend``), never the opacities, scales or rotations. The depth term still reaches
    them through the target depth, so it is checked with the targets' render held fixed."""
    make_capture(tmp_path, views=4, lights=2, size=16)
    dataset = OLATDataset(tmp_path)
    results = {}
    for mode in ("blend", "centres"):
        cfg = make_config("diamond", overrides={
            "iterations": 10, "num_gaussians": 200, "batch_size": 1, "lambda_lpips": 0.0, "densify": False,
            "device": "cpu", "mv_pixels_per_pair": 64, "mv_pairs_per_step": 4, "mv_target_mode": "random",
            "mv_source_gradient": mode})
        trainer = Trainer(cfg, [ImageSource(dataset)], None, show_progress=False)
        scene = trainer.build_scene()
        _, target, light_pos, light_rgb = trainer.draw_batch(0)
        render = scene.render(target.viewmats, target.Ks, trainer.width, trainer.height, light_pos, light_rgb)
        _hold_target_renders(scene)
        value = trainer.multiview_terms(scene, render, target, 3)[term]
        scene.zero_grad()
        grads = dict(zip(("means", "opacities", "scales", "quats"), torch.autograd.grad(
            value, [scene.gaussians.params[name] for name in ("means", "opacities", "scales", "quats")],
            allow_unused=True)))
        results[mode] = (value.detach(), grads)
    (blend_value, blend), (centres_value, centres) = results["blend"], results["centres"]
    assert blend_value > 0 and torch.allclose(blend_value, centres_value, rtol=1e-5)  # one raster or another
    assert centres["means"].abs().sum() > 0 and torch.allclose(centres["means"], blend["means"], atol=1e-7)
    for name in ("opacities", "scales", "quats"):
        assert blend[name] is not None and blend[name].abs().sum() > 0
        assert centres[name] is None or not centres[name].any()


def _hold_target_renders(scene) -> None:
    """Make ``scene``'s plain geometry renders (the target views') carry no gradient; centres-only ones keep theirs."""
    render_geometry = scene.render_geometry

    def held(*args, centres_only=False, **kwargs):
        raster = render_geometry(*args, centres_only=centres_only, **kwargs)
        if centres_only:
            return raster
        return type(raster)(**{field: value.detach() if isinstance(value, torch.Tensor) else value
                               for field, value in vars(raster).items()})

    scene.render_geometry = held


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_matches_cpu():
    src, tgt, src_depth, tgt_depth, sil, mask = offset_plane_pair()
    cfg = MultiViewConfig(occlusion_tol=1.0, sil_threshold=0.3)
    results = []
    for device in ("cpu", "cuda"):
        uv = sample_foreground_pixels(mask.to(device), 50, torch.Generator().manual_seed(0)).to(torch.float64)
        cams = [tuple(x.to(device) for x in view) for view in (src, tgt)]
        depth = src_depth.detach().to(device).requires_grad_(True)  # a fresh leaf on each device
        terms = run(*cams, depth, tgt_depth.to(device), cfg, uv=uv, sil=sil.to(device))
        (terms.silhouette + terms.depth).backward()
        results.append((terms.silhouette.item(), terms.depth.item(), depth.grad.cpu()))
        assert terms.silhouette.device.type == device
    assert results[0][0] == pytest.approx(results[1][0], rel=1e-9)
    assert results[0][1] == pytest.approx(results[1][1], rel=1e-9)
    assert torch.allclose(results[0][2], results[1][2], rtol=1e-7, atol=1e-12)
    pairs = sample_view_pairs(ring_centres(6).cuda(), 5, "nearest-k", 2, torch.Generator().manual_seed(0))
    assert pairs.device.type == "cuda" and pairs.shape == (5, 2)
