"""Novel-view model: Plucker rays, harmonic embedding, zero-initialised Free3D layers, shared noise."""

from __future__ import annotations

import math

import pytest
import torch
from tiny_models import TINY_NVS, tiny_vae

from diamond_sss.data.conventions import (
    intrinsics_from_fov,
    look_at_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    pixel_grid,
    unproject_pixels,
)
from diamond_sss.diffusion.common.schedulers import make_ddim_scheduler, make_ddpm_scheduler
from diamond_sss.diffusion.nvs.model import NVSBatch, NVSConfig, NVSModel, shared_noise
from diamond_sss.diffusion.nvs.pipeline import NovelViewPipeline
from diamond_sss.diffusion.nvs.rays import (
    harmonic_embedding,
    plucker_rays,
    ray_embedding,
    relative_spherical_pose,
    view_angle_degrees,
)

TINY = {**TINY_NVS, "warp_hint": False}
"""The base model (no warp hint); the hint is tested in test_nvs_warp.py."""


def camera(azimuth: float, elevation: float = 0.3, radius: float = 4.0) -> torch.Tensor:
    eye = torch.tensor(
        [
            radius * math.cos(azimuth) * math.cos(elevation),
            radius * math.sin(azimuth) * math.cos(elevation),
            radius * math.sin(elevation),
        ]
    )
    return opengl_c2w_to_opencv_w2c(
        look_at_opengl_c2w(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    ).float()


def tiny_batch(objects: int = 2, views: int = 3, size: int = 16, seed: int = 0) -> NVSBatch:
    g = torch.Generator().manual_seed(seed)
    target_w2c = torch.stack(
        [torch.stack([camera(0.4 * v + o) for v in range(views)]) for o in range(objects)]
    )
    K = intrinsics_from_fov(0.6, size, size).expand(objects, views, 3, 3).clone()
    return NVSBatch(
        reference=torch.rand(objects, 4, size, size, generator=g),
        reference_w2c=torch.stack([camera(o - 0.7) for o in range(objects)]),
        target_w2c=target_w2c,
        target_K=K,
        targets=torch.rand(objects, views, 4, size, size, generator=g),
    )


def test_plucker_rays_of_identical_cameras_are_pixel_directions_with_zero_moment():
    w2c = camera(0.3)
    K = intrinsics_from_fov(0.6, 8, 6)
    rays = plucker_rays(w2c, w2c, K, 6, 8)
    assert rays.shape == (6, 6, 8)
    uv = pixel_grid(6, 8)
    expected = torch.cat([uv, torch.ones(6, 8, 1)], -1) @ torch.linalg.inv(K).T
    expected = expected / expected.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(rays[:3].permute(1, 2, 0), expected, atol=1e-5, rtol=0)
    assert rays[3:].abs().max() < 1e-5


def test_plucker_lines_contain_the_points_seen_at_each_pixel():
    target, reference = camera(1.1, 0.5), camera(-0.4, 0.1)
    K = intrinsics_from_fov(0.6, 5, 4)
    rays = plucker_rays(target, reference, K, 4, 5).permute(1, 2, 0).reshape(-1, 6)
    uv = pixel_grid(4, 5).reshape(-1, 2)
    depth = torch.linspace(2.0, 5.0, uv.shape[0])
    world = unproject_pixels(uv, depth, target, K)  # points the target camera sees at those pixels
    in_reference = world @ reference[:3, :3].T + reference[:3, 3]
    d, m = rays[:, :3], rays[:, 3:]
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(len(d)), atol=1e-5, rtol=0)
    # a point X lies on the line (d, m) iff X x d = m
    torch.testing.assert_close(torch.linalg.cross(in_reference, d, dim=-1), m, atol=1e-4, rtol=0)


def test_plucker_rays_are_invariant_to_the_world_frame():
    target, reference = camera(0.9), camera(0.1)
    K = intrinsics_from_fov(0.6, 4, 4)
    angle = 0.7
    rigid = torch.eye(4)
    rigid[:2, :2] = torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    rigid[:3, 3] = torch.tensor([0.3, -1.0, 2.0])
    moved = [w @ torch.linalg.inv(rigid) for w in (target, reference)]
    torch.testing.assert_close(
        plucker_rays(*moved, K, 4, 4), plucker_rays(target, reference, K, 4, 4), atol=1e-4, rtol=0
    )


def test_harmonic_embedding_layout_and_ray_embedding_channels():
    x = torch.tensor([[0.5, -1.0]])
    emb = harmonic_embedding(x, n_frequencies=3)
    expected = [
        math.sin(0.5),
        math.sin(1.0),
        math.sin(2.0),
        math.sin(-1.0),
        math.sin(-2.0),
        math.sin(-4.0),
        math.cos(0.5),
        math.cos(1.0),
        math.cos(2.0),
        math.cos(-1.0),
        math.cos(-2.0),
        math.cos(-4.0),
        0.5,
        -1.0,
    ]
    torch.testing.assert_close(emb[0], torch.tensor(expected))
    K = intrinsics_from_fov(0.6, 4, 4)
    rays = plucker_rays(camera(0.2), camera(0.0), K, 4, 4)
    embedded = ray_embedding(camera(0.2), camera(0.0), K, 4, 4)
    # along the channels: sin(2^k r_c) at 6 c + k for the 6 Plucker coordinates and 6 frequencies, the cosines
    # after them, the rays themselves last (6 * (2 * 6 + 1) = 78 channels)
    phase = (rays[:, None] * 2.0 ** torch.arange(6.0)[None, :, None, None]).reshape(36, 4, 4)
    assert embedded.shape == (78, 4, 4)
    torch.testing.assert_close(embedded, torch.cat([phase.sin(), phase.cos(), rays]))


def test_relative_pose_and_view_angle_of_known_cameras():
    a, b = camera(0.0, 0.0), camera(math.pi / 2, 0.0, radius=5.0)
    pose = relative_spherical_pose(b, a)
    torch.testing.assert_close(pose, torch.tensor([0.0, 1.0, 0.0, 1.0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(view_angle_degrees(b, a), torch.tensor(90.0), atol=1e-3, rtol=0)


def _set_random(module: torch.nn.Module, names: tuple[str, ...], seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    for name, p in module.named_parameters():
        if any(n in name for n in names):
            with torch.no_grad():
                p.copy_(torch.randn(p.shape, generator=g) * 0.2)


def _denoise(
    model: NVSModel, batch: NVSBatch, rays_scale: float = 1.0, views: int | None = None
) -> torch.Tensor:
    b, v = batch.target_w2c.shape[:2]
    g = torch.Generator().manual_seed(3)
    ref = model.encode(batch.reference).repeat_interleave(v, 0)
    rays, pose = model.conditioning(batch, ref)
    context = model.context(model.reference_encoder(ref), pose, torch.zeros(b * v, dtype=torch.bool))
    noisy = torch.randn(ref.shape, generator=g)
    t = torch.full((b * v,), 500)
    return model.denoise(noisy, t, ref, context, rays * rays_scale, views or v)


def test_fresh_ray_conditioning_and_multi_view_layers_leave_the_unet_unchanged():
    torch.manual_seed(0)
    model = NVSModel(NVSConfig(**TINY)).eval()
    _set_random(model.unet, ("conv2.weight", "proj_out.weight"), seed=1)  # make the base UNet non-trivial
    batch = tiny_batch()
    with torch.no_grad():
        base = _denoise(model, batch, rays_scale=0.0, views=1)  # no rays, no cross-view attention
        grafted = _denoise(model, batch)
    assert base.abs().max() > 1e-3
    torch.testing.assert_close(grafted, base, atol=1e-6, rtol=0)
    # once trained (non-zero), the same layers do change the output
    _set_random(model.unet, ("ray_proj", "attn_mv.to_out"), seed=2)
    with torch.no_grad():
        assert (_denoise(model, batch) - base).abs().max() > 1e-3


def test_multi_view_attention_mixes_only_views_of_the_same_object():
    torch.manual_seed(0)
    model = NVSModel(NVSConfig(**TINY)).eval()
    _set_random(model.unet, ("conv2.weight", "proj_out.weight", "attn_mv.to_out", "ray_proj"), seed=1)
    batch = tiny_batch(objects=2, views=3)
    with torch.no_grad():
        out = _denoise(model, batch)
        batch.target_w2c[1, 0] = camera(2.5)  # change one view of object 1
        changed = _denoise(model, batch)
    diff = (changed - out).flatten(1).abs().amax(dim=1)
    assert diff[:3].max() < 1e-6  # object 0 untouched
    assert diff[4:].min() > 1e-6  # the other views of object 1 see the change through multi-view attention


def test_shared_noise_is_identical_across_views_and_distinct_across_objects():
    noise = shared_noise(3, 4, (2, 5, 5), generator=torch.Generator().manual_seed(0))
    assert noise.shape == (3, 4, 2, 5, 5)
    for o in range(3):
        for v in range(1, 4):
            assert torch.equal(noise[o, v], noise[o, 0])
    assert not torch.allclose(noise[0, 0], noise[1, 0])


def test_sampling_is_deterministic_and_shared_noise_gives_identical_views_for_identical_cameras():
    torch.manual_seed(0)
    model = NVSModel(NVSConfig(**TINY)).eval()
    _set_random(model.unet, ("conv2.weight", "proj_out.weight", "conv_out.weight"), seed=1)
    batch = tiny_batch(objects=1, views=2)
    batch.target_w2c[0, 1] = batch.target_w2c[0, 0]
    a = NovelViewPipeline(model)(batch, num_steps=2, generator=torch.Generator().manual_seed(5))
    b = NovelViewPipeline(model)(batch, num_steps=2, generator=torch.Generator().manual_seed(5))
    assert a.rgb.shape == (2, 16, 16, 3) and a.alpha.shape == (2, 16, 16, 1)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.alpha, b.alpha)
    torch.testing.assert_close(a.rgb[0], a.rgb[1], atol=1e-5, rtol=0)
    resized = NovelViewPipeline(model)(batch, num_steps=2, generator=torch.Generator().manual_seed(5), size=24)
    assert resized.rgb.shape == (2, 24, 24, 3) and resized.alpha.shape == (2, 24, 24, 1)


def test_latent_space_round_trip_uses_the_vae_scale():
    torch.manual_seed(0)
    vae = tiny_vae(levels=4)
    model = NVSModel(NVSConfig(**{**TINY, "space": "latent", "image_size": 32}), vae=vae).eval()
    rgba = torch.rand(2, 4, 32, 32)
    with torch.no_grad():
        z = model.encode(rgba)
        expected = vae.encode(rgba[:, :3] * 2 - 1).latent_dist.mode() * 0.18215
        out = model.decode(z)
        colour = ((vae.decode(z / 0.18215).sample + 1) / 2).clamp(0, 1)
    assert z.shape == (2, 4, 4, 4)
    torch.testing.assert_close(z, expected)
    # a 3-channel VAE: colour from the unscaled latents, alpha where any channel exceeds 1/255
    torch.testing.assert_close(out, torch.cat([colour, (colour.amax(1, keepdim=True) > 1 / 255).float()], 1))


def test_noise_schedule_is_the_ldm_linear_schedule():
    betas = make_ddpm_scheduler(NVSConfig().scheduler).betas
    expected = torch.linspace(0.00085**0.5, 0.012**0.5, 1000, dtype=torch.float64) ** 2
    torch.testing.assert_close(betas.double(), expected, atol=1e-7, rtol=0)


def test_save_load_round_trip(tmp_path):
    torch.manual_seed(0)
    model = NVSModel(NVSConfig(**TINY))
    _set_random(model, ("ray_proj",), seed=4)
    model.save(tmp_path)
    loaded = NVSModel.load(tmp_path)
    for (k, a), (_, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
        assert torch.equal(a, b), k
    # fp16 storage (the shipped weights): loaded back as fp32, equal to the fp16-rounded weights.
    model.save(tmp_path / "half", half=True)
    halved = NVSModel.load(tmp_path / "half")
    for (k, a), (_, b) in zip(model.state_dict().items(), halved.state_dict().items()):
        assert b.dtype == a.dtype, k
        assert torch.equal(b, a.half().float() if a.is_floating_point() else a), k


def test_width_and_depth_options_build_a_larger_model_that_round_trips(tmp_path):
    small = NVSModel(NVSConfig(**TINY))
    large = NVSModel(NVSConfig(**{**TINY, "block_out_channels": (32, 64), "layers_per_block": 2}))
    counts = {name: sum(p.numel() for p in model.parameters()) for name, model in (("small", small), ("large", large))}
    assert counts["large"] > 3 * counts["small"]
    large.save(tmp_path)
    loaded = NVSModel.load(tmp_path)
    assert loaded.config == large.config
    for (key, a), (_, b) in zip(large.state_dict().items(), loaded.state_dict().items()):
        assert torch.equal(a, b), key


def test_bad_inputs_give_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="space"):
        NVSConfig(space="voxel")
    with pytest.raises(ValueError, match="prediction_type"):
        NVSConfig(prediction_type="sample")
    with pytest.raises(ValueError, match="needs a VAE"):
        NVSModel(NVSConfig(**{**TINY, "space": "latent"}))
    with pytest.raises(ValueError, match=r"one entry per UNet level \(2"):
        NVSConfig(**{**TINY, "block_out_channels": (16, 32, 32)})
    with pytest.raises(ValueError, match=r"multiples of norm_num_groups=8, got \(16, 20\) \(\[20\] are not\)"):
        NVSConfig(**{**TINY, "block_out_channels": (16, 20)})
    with pytest.raises(ValueError, match="layers_per_block"):
        NVSConfig(**{**TINY, "layers_per_block": 0})
    with pytest.raises(FileNotFoundError, match="config.json"):
        NVSModel.load(tmp_path)
    batch = tiny_batch()
    batch.target_K = batch.target_K[:, :1]
    with pytest.raises(ValueError, match="target_K"):
        batch.validate()


def test_ddim_sampling_with_an_oracle_denoiser_recovers_the_clean_views():
    torch.manual_seed(0)
    model = NVSModel(NVSConfig(**TINY)).eval()
    batch = tiny_batch(objects=1, views=2)
    clean = torch.rand(2, 4, 16, 16) * 2 - 1
    alphas = make_ddim_scheduler(model.config.scheduler, model.config.sample_clip_range).alphas_cumprod

    def oracle(noisy, timesteps, reference, context, rays, num_views, hint=None):
        a = alphas[timesteps].reshape(-1, 1, 1, 1)
        return (noisy - a.sqrt() * clean.repeat(noisy.shape[0] // 2, 1, 1, 1)) / (1 - a).sqrt()

    model.denoise = oracle
    out = NovelViewPipeline(model)(batch, num_steps=10, guidance_scale=2.0, generator=torch.Generator().manual_seed(0))
    rgba = torch.cat([out.rgb, out.alpha], dim=-1).permute(0, 3, 1, 2)
    torch.testing.assert_close(rgba, (clean + 1) / 2, atol=1e-4, rtol=0)
