"""Relighting diffusion model: SH light code, shapes, v-prediction algebra, saving/loading, bad inputs."""

from __future__ import annotations

import math

import pytest
import torch
from tiny_models import TINY_RELIGHT, tiny_sd_unet, tiny_vae

from diamond_sss.data.conventions import look_at_opengl_c2w, opengl_c2w_to_opencv_w2c
from diamond_sss.diffusion.common.schedulers import SchedulerConfig, make_ddpm_scheduler
from diamond_sss.diffusion.common.targets import predicted_clean, v_target
from diamond_sss.diffusion.relight.conditioning import conditioning_image, image_to_model, model_to_image
from diamond_sss.diffusion.relight.config import RelightModelConfig
from diamond_sss.diffusion.relight.hint import (
    diffused_shading,
    direction_from_code,
    fit_scattering,
    lambertian_hint,
)
from diamond_sss.diffusion.relight.light import light_code
from diamond_sss.diffusion.relight.model import RelightDiffusion
from diamond_sss.diffusion.relight.pipeline import RelightPipeline


def tiny_config(**overrides) -> RelightModelConfig:
    return RelightModelConfig(**{**TINY_RELIGHT, **overrides})


def tiny_model(seed: int = 0, **overrides) -> RelightDiffusion:
    return RelightDiffusion.from_config(tiny_config(**overrides), seed=seed)


def random_inputs(batch: int = 2, size: int = 16, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(batch, 3, size, size, generator=g),
        torch.randint(0, 1000, (batch,), generator=g),
        torch.rand(batch, 8, size, size, generator=g) * 2 - 1,
        torch.randn(batch, 10, generator=g),
        torch.randn(batch, 10, generator=g),
    )


def camera_w2c(eye):
    return opengl_c2w_to_opencv_w2c(look_at_opengl_c2w(torch.tensor(eye), torch.zeros(3)))


def test_light_code_closed_form():
    c0, c1 = 0.5 * math.sqrt(1 / math.pi), math.sqrt(3 / (4 * math.pi))
    w2c = camera_w2c([0.0, 0.0, 4.0])  # camera on +z looking at the origin: OpenCV z = world -z
    towards_camera = light_code(torch.tensor([0.0, 0.0, 5.0]), w2c, torch.zeros(3), 2.0)
    # Direction in the camera frame: (0, 0, -1). Y = [c0, -c1 y, c1 z, -c1 x, ...], distance 5 / 2.
    c2_20 = 0.25 * math.sqrt(5 / math.pi) * 2.0  # Y_2^0 = 0.3154 (2 z^2 - x^2 - y^2) at z = -1
    expected = torch.tensor([c0, 0.0, -c1, 0.0, 0.0, 0.0, c2_20, 0.0, 0.0, 2.5])
    assert torch.allclose(towards_camera, expected, atol=1e-5)
    right = light_code(torch.tensor([3.0, 0.0, 0.0]), w2c, torch.zeros(3), 1.0)
    # World +x is the camera's right (OpenCV +x): Y_1^1 = -c1 x, Y_2^2 = 0.5463 (x^2 - y^2).
    assert right[3] == pytest.approx(-c1, abs=1e-5) and right[8] == pytest.approx(0.5462742, abs=1e-5)
    assert right[9] == pytest.approx(3.0)
    # Orthonormality of the 9 bases: a quadrature over many directions gives the identity.
    dirs = torch.nn.functional.normalize(
        torch.randn(200_000, 3, generator=torch.Generator().manual_seed(0)), dim=-1
    )
    codes = light_code(dirs * 3.0, torch.eye(4).expand(len(dirs), 4, 4), torch.zeros(3), 1.0)[:, :9]
    gram = codes.T @ codes * (4 * math.pi / len(dirs))
    assert torch.allclose(gram, torch.eye(9), atol=0.03)


def test_light_code_rejects_bad_input():
    with pytest.raises(ValueError, match="light_positions"):
        light_code(torch.zeros(2), torch.eye(4), torch.zeros(3), 1.0)
    with pytest.raises(ValueError, match="centre"):
        light_code(torch.zeros(3), torch.eye(4), torch.zeros(3), 1.0)


def test_v_prediction_round_trip():
    alphas = make_ddpm_scheduler(SchedulerConfig()).alphas_cumprod
    g = torch.Generator().manual_seed(1)
    clean, noise = torch.randn(4, 3, 8, 8, generator=g), torch.randn(4, 3, 8, 8, generator=g)
    t = torch.tensor([0, 10, 500, 999])
    a = alphas[t].sqrt().reshape(-1, 1, 1, 1)
    s = (1 - alphas[t]).sqrt().reshape(-1, 1, 1, 1)
    noisy = a * clean + s * noise
    v = v_target(clean, noise, alphas, t)
    assert torch.allclose(predicted_clean(noisy, v, alphas, t), clean, atol=1e-5)
    # The training scheduler adds noise the same way.
    assert torch.allclose(make_ddpm_scheduler(SchedulerConfig()).add_noise(clean, noise, t), noisy, atol=1e-6)


def test_image_space_round_trip():
    linear = torch.rand(2, 5, 6, 3)
    assert torch.allclose(model_to_image(image_to_model(linear)), linear, atol=1e-5)


def test_forward_and_sampling_shapes_are_seeded():
    model = tiny_model().eval()
    x, t, cond, code, src = random_inputs()
    assert model(x, t, cond, code, src).shape == x.shape
    first = RelightPipeline(model).sample(cond, code, src, num_steps=3, generator=torch.Generator().manual_seed(7))
    again = RelightPipeline(model).sample(cond, code, src, num_steps=3, generator=torch.Generator().manual_seed(7))
    assert first.shape == (2, 3, 16, 16) and torch.equal(first, again)
    assert float(first.abs().max()) <= 1.0
    assert torch.equal(tiny_model(seed=0).unet.conv_in.weight, model.unet.conv_in.weight)
    assert not torch.equal(tiny_model(seed=1).unet.conv_in.weight, model.unet.conv_in.weight)


def test_light_code_reaches_the_output():
    model = tiny_model().eval()
    torch.nn.init.normal_(model.unet.conv_out.weight, std=0.1)
    x, t, cond, code, src = random_inputs()
    with torch.no_grad():
        assert not torch.allclose(model(x, t, cond, code, src), model(x, t, cond, code + 1.0, src))


def test_source_light_option():
    """With the option the source light's code reaches the output; without it (and with no hint) it is ignored."""
    x, t, cond, code, src = random_inputs()
    outputs = {}
    for use in (True, False):
        model = tiny_model(use_source_light=use, shading_hint=False, residual=False).eval()
        with torch.no_grad():
            outputs[use] = model(x, t, cond, code, src), model(x, t, cond, code, src + 1.0)
    assert outputs[True][0].shape == x.shape and not torch.allclose(*outputs[True])
    assert torch.equal(*outputs[False])
    with pytest.raises(ValueError, match="source light"):
        tiny_model(use_source_light=True, shading_hint=False, residual=False)(x, t, cond, code)


def test_bad_inputs_have_clear_errors(tmp_path):
    model = tiny_model()
    x, t, cond, code, src = random_inputs()
    with pytest.raises(ValueError, match="conditioning must be \\[B, 8"):
        model(x, t, cond[:, :5], code, src)
    with pytest.raises(ValueError, match="target_code must be"):
        model(x, t, cond, code[:, :9], src)
    with pytest.raises(FileNotFoundError, match="has no config.json"):
        RelightDiffusion.load(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="not a diffusers Stable Diffusion folder"):
        RelightDiffusion.from_pretrained_sd(tmp_path)
    with pytest.raises(ValueError, match="must have shape \\[B,H,W,3\\]"):
        conditioning_image(
            torch.zeros(1, 8, 8, 4),
            torch.zeros(1, 8, 8, 1),
            torch.zeros(1, 8, 8, 3),
            torch.zeros(1, 8, 8, 1),
            8,
        )
    normals = torch.zeros(1, 8, 8, 3)
    normals[0, 3, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="normals map has non-finite values"):
        conditioning_image(
            torch.zeros(1, 8, 8, 3), torch.zeros(1, 8, 8, 1), normals, torch.ones(1, 8, 8, 1), 8
        )
    with pytest.raises(ValueError, match="resolution"):
        tiny_config(resolution=15)


def test_save_load_round_trip(tmp_path):
    model = tiny_model().eval()
    model.save(tmp_path / "m")
    loaded = RelightDiffusion.load(tmp_path / "m")
    x, t, cond, code, src = random_inputs()
    with torch.no_grad():
        assert torch.equal(model(x, t, cond, code, src), loaded(x, t, cond, code, src))
    assert loaded.weights_hash() == model.weights_hash()
    assert tiny_model(seed=3).weights_hash() != model.weights_hash()


def test_from_local_stable_diffusion_folder(tmp_path):
    from diffusers import UNet2DConditionModel

    torch.manual_seed(0)
    tiny_sd_unet(in_channels=4, cross_attention_dim=12).save_pretrained(tmp_path / "sd" / "unet")
    tiny_vae().save_pretrained(tmp_path / "sd" / "vae")
    sd_unet = UNet2DConditionModel.from_pretrained(tmp_path / "sd" / "unet")
    model = RelightDiffusion.from_pretrained_sd(tmp_path / "sd", tiny_config(resolution=16)).eval()
    assert model.config.space == "latent" and model.config.cross_attention_dim == 12
    assert torch.equal(model.unet.conv_in.weight, sd_unet.conv_in.weight)  # pretrained weights kept
    latent = model.encode(torch.zeros(1, 3, 16, 16))
    assert latent.shape == (1, 4, 8, 8) and model.sample_shape(1) == (1, 4, 8, 8)
    _, _, cond, code, src = random_inputs(batch=1)
    out = RelightPipeline(model).sample(cond, code, src, num_steps=2, generator=torch.Generator().manual_seed(0))
    assert out.shape == (1, 3, 16, 16) and bool(torch.isfinite(out).all())
    model.save(tmp_path / "latent")
    with torch.no_grad():
        t = torch.tensor([5])
        assert torch.equal(
            RelightDiffusion.load(tmp_path / "latent")(latent, t, cond, code, src),
            model(latent, t, cond, code, src),
        )


def test_direction_from_code_inverts_the_light_code():
    g = torch.Generator().manual_seed(4)
    positions = torch.randn(50, 3, generator=g) * 3.0
    center = torch.tensor([0.1, -0.2, 0.3])
    w2c = camera_w2c([1.0, 2.0, 4.0]).float().expand(50, 4, 4)
    direction, distance = direction_from_code(light_code(positions, w2c, center, 2.0))
    offset = (w2c[:, :3, :3] @ (positions - center).unsqueeze(-1)).squeeze(-1)
    assert torch.allclose(direction, torch.nn.functional.normalize(offset, dim=-1), atol=1e-5)
    assert torch.allclose(distance[:, 0], offset.norm(dim=-1) / 2.0, atol=1e-5)


def test_lambertian_hint_known_answer():
    # A disc facing the camera (OpenCV normal (0, 0, -1)) of linear radiance 0.2 under a light at 60 degrees
    # from the normal: relit by a light along the normal at the same distance, cos goes 0.5 -> 1, so 0.4.
    size = 8
    mask = torch.zeros(1, size, size, 1)
    mask[:, 2:6, 2:6] = 1.0
    normals = torch.tensor([0.0, 0.0, -1.0]).expand(1, size, size, 3) * mask
    cond = conditioning_image(torch.full((1, size, size, 3), 0.2) * mask, mask, normals, mask, size)
    w2c = torch.eye(4)[None]
    at_60 = light_code(
        torch.tensor([[math.sin(math.pi / 3), 0.0, -math.cos(math.pi / 3)]]) * 3.0, w2c, torch.zeros(3), 1.0
    )
    frontal = light_code(torch.tensor([[0.0, 0.0, -3.0]]), w2c, torch.zeros(3), 1.0)
    hint = model_to_image(lambertian_hint(cond, frontal, at_60))
    inside = mask[..., 0] > 0.5
    assert torch.allclose(hint[inside], torch.full_like(hint[inside], 0.4), atol=1e-4)
    assert float(hint[~inside].abs().max()) == 0.0
    # Screen-space diffusion inside the mask leaves uniform shading unchanged.
    diffused = model_to_image(lambertian_hint(cond, frontal, at_60, blur_sigmas=(1.5,)))
    assert torch.allclose(diffused, hint, atol=1e-4)
    # Twice as far away: a quarter of the light.
    far = light_code(torch.tensor([[0.0, 0.0, -6.0]]), w2c, torch.zeros(3), 1.0)
    assert torch.allclose(
        model_to_image(lambertian_hint(cond, far, at_60))[inside], torch.tensor(0.1), atol=1e-4
    )


def test_hint_fits_the_scattering_of_the_source():
    # A sphere rendered with wrap 0.5 and a 2 px diffusion under one light: the hint, choosing from a grid that
    # holds that pair, predicts the same rendering under another light exactly, and a Lambertian-only grid not.
    size = 24
    ys, xs = torch.meshgrid(torch.linspace(-1.2, 1.2, size), torch.linspace(-1.2, 1.2, size), indexing="ij")
    inside = (xs.square() + ys.square() < 1.0).float()
    z = -(1.0 - xs.square() - ys.square()).clamp_min(0.0).sqrt()
    normals = torch.stack([xs, ys, z], dim=-1)[None] * inside[None, ..., None]
    mask = inside[None, ..., None]
    w2c = torch.eye(4)[None]
    source_code = light_code(torch.tensor([[2.5, -1.0, -1.5]]), w2c, torch.zeros(3), 1.0)
    target_code = light_code(torch.tensor([[-2.0, 0.5, -2.0]]), w2c, torch.zeros(3), 1.0)
    keep = mask.permute(0, 3, 1, 2)
    normals_chw = normals.permute(0, 3, 1, 2)
    albedo = torch.tensor([0.9, 0.6, 0.4])[None, :, None, None] * 3.0

    def render(code):
        return (albedo * diffused_shading(normals_chw, keep, code, wrap=0.5, blur_sigma=2.0)).clamp(0.0, 1.0)

    cond = conditioning_image(render(source_code).permute(0, 2, 3, 1), mask, normals, mask, size)
    truth = render(target_code)
    fitted = model_to_image(
        lambertian_hint(cond, target_code, source_code, blur_sigmas=(0.0, 1.0, 2.0, 4.0), wraps=(0.0, 0.5, 1.0))
    ).permute(0, 3, 1, 2)
    assert torch.allclose(fitted, truth, atol=1e-4)
    lambertian = model_to_image(lambertian_hint(cond, target_code, source_code)).permute(0, 3, 1, 2)
    assert float((lambertian - truth).abs().max()) > 0.05
    fit = fit_scattering(cond, source_code, blur_sigmas=(0.0, 1.0, 2.0, 4.0), wraps=(0.0, 0.5, 1.0))
    assert (float(fit.wrap), float(fit.sigma)) == (0.5, 2.0)
    assert torch.allclose(fit.albedo.flatten(), albedo.flatten(), atol=1e-4)


def test_one_fit_per_source_gives_the_hint_of_each_pair():
    model = tiny_model().eval()
    generator = torch.Generator().manual_seed(4)
    single = torch.rand(1, 8, 16, 16, generator=generator) * 2.0 - 1.0
    positions = torch.randn(5, 3, generator=generator) * 3.0
    codes = light_code(positions, torch.eye(4).expand(5, 4, 4), torch.zeros(3), 1.0)
    source_code = codes[:1].expand(4, -1)
    cond = single.expand(4, -1, -1, -1)
    fitted_once = model.hint(cond, codes[1:], source_code, fit=model.scattering_fit(single, codes[:1]).expand(4))
    assert torch.allclose(fitted_once, model.hint(cond, codes[1:], source_code), atol=1e-6)
    mixed = torch.cat([single, torch.rand(1, 8, 16, 16, generator=generator) * 2.0 - 1.0])
    fit = model.scattering_fit(mixed, codes[:2])
    assert torch.allclose(
        model.hint(mixed, codes[2:4], codes[:2], fit=fit), model.hint(mixed, codes[2:4], codes[:2]), atol=1e-6
    )
    with pytest.raises(ValueError, match="one entry per image, got 4, 4 and 1"):
        model.hint(cond, codes[1:], source_code, fit=model.scattering_fit(single, codes[:1]))
    empty = single.clone()
    empty[:, 7] = -1.0
    assert torch.equal(model.hint(empty, codes[1:2], codes[:1]), torch.full((1, 3, 16, 16), -1.0))


def test_config_reads_models_saved_with_one_hint_blur():
    legacy = RelightModelConfig().to_dict()
    del legacy["hint_blurs"], legacy["hint_wraps"]
    legacy["hint_blur"] = 0.03125
    config = RelightModelConfig.from_dict(legacy)
    assert config.hint_blurs == (0.03125,) and config.hint_wraps == (0.0,)
    assert RelightModelConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="hint_wraps must be a non-empty list of numbers"):
        RelightModelConfig(hint_wraps=())
    with pytest.raises(ValueError, match=r"hint_blurs must be a non-empty list of numbers, got \('0.1',\)"):
        RelightModelConfig.from_dict({**config.to_dict(), "hint_blurs": ["0.1"]})


def test_residual_model_adds_the_hint_back():
    from dataclasses import replace

    model = tiny_model().eval()
    plain = RelightDiffusion(replace(model.config, residual=False), model.unet, model.controlnet).eval()
    plain.light_tokens = model.light_tokens
    _, _, cond, code, src = random_inputs(batch=2)
    noise = torch.randn(model.sample_shape(2), generator=torch.Generator().manual_seed(2)) * 0.1
    residual = RelightPipeline(model).sample(cond, code, src, num_steps=2, noise=noise)
    direct = RelightPipeline(plain).sample(cond, code, src, num_steps=2, noise=noise)
    hint = model.hint(cond, code, src)
    unclamped = (residual.abs() < 0.99) & (direct.abs() < 0.99)
    assert bool(unclamped.any())
    assert torch.allclose((residual - direct)[unclamped], hint[unclamped], atol=1e-5)
    with pytest.raises(ValueError, match="needs shading_hint"):
        tiny_config(shading_hint=False)


def test_hint_blur_preserves_constants_and_spreads_light():
    from diamond_sss.diffusion.relight.hint import gaussian_blur

    constant = torch.full((1, 2, 9, 9), 0.7)
    assert torch.allclose(gaussian_blur(constant, 1.5), constant, atol=1e-6)
    impulse = torch.zeros(1, 1, 15, 15)
    impulse[0, 0, 7, 7] = 1.0
    blurred = gaussian_blur(impulse, 1.0)
    assert float(blurred.sum()) == pytest.approx(1.0, abs=1e-5)
    # Separable Gaussian: the ratio of neighbours one pixel apart is exp(-1/2), and of diagonal ones exp(-1).
    assert float(blurred[0, 0, 7, 8] / blurred[0, 0, 7, 7]) == pytest.approx(math.exp(-0.5), rel=1e-4)
    assert float(blurred[0, 0, 8, 8] / blurred[0, 0, 7, 7]) == pytest.approx(math.exp(-1.0), rel=1e-4)
    assert torch.equal(gaussian_blur(impulse, 0.0), impulse)


def test_the_pipeline_averages_samples_in_model_space_and_resizes():
    model = tiny_model().eval()
    _, _, cond, code, src = random_inputs(batch=2)
    noise = torch.randn(2, *model.sample_shape(2), generator=torch.Generator().manual_seed(3))
    pipeline = RelightPipeline(model)
    single = [pipeline.sample(cond, code, src, num_steps=2, noise=n) for n in noise]
    out = pipeline(cond, code, src, num_steps=2, noise=noise, samples=2)
    assert out.alpha is None and out.rgb.shape == (2, 16, 16, 3)
    torch.testing.assert_close(out.rgb, model_to_image((single[0] + single[1]) / 2), atol=1e-6, rtol=0)
    assert pipeline(cond, code, src, num_steps=2, noise=noise, samples=2, size=(24, 20)).rgb.shape == (2, 24, 20, 3)
    with pytest.raises(ValueError, match="expected 3"):
        pipeline(cond, code, src, num_steps=2, noise=noise, samples=3)
