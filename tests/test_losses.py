"""Tests of diamond_sss.losses: photometric terms, regularisers and the optional LPIPS network."""

from __future__ import annotations

import math

import pytest
import torch
from safetensors.torch import save_file

from diamond_sss.data.conventions import (
    camera_centers,
    intrinsics_from_fov,
    look_at_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    pixel_grid,
    unproject_pixels,
)
from diamond_sss.losses import (
    LPIPS,
    base_color_prior_loss,
    bilateral_smoothness_loss,
    convert_lpips_state_dict,
    dssim_loss,
    enhancement_loss,
    enhancement_target,
    incident_light_loss,
    l1_loss,
    load_lpips,
    mask_bce_loss,
    mask_entropy_loss,
    normal_consistency_loss,
    normals_from_depth,
    photometric_loss,
    raytrace_visibility_loss,
    rmse_per_image,
    ssim_per_image,
)
from diamond_sss.losses import lpips as lpips_module
from diamond_sss.losses.lpips import LIN_CHANNELS, VGG16_CONVS, expected_shapes
from diamond_sss.utils.logs import reset_warnings


def _images(
    batch: int = 2, size: int = 16, channels: int = 3, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    a = torch.rand(batch, size, size, channels, generator=gen)
    b = torch.rand(batch, size, size, channels, generator=gen)
    return a, b


# ----------------------------------------------------------------------------- photometric


def test_l1_known_value_and_weights():
    pred = torch.zeros(2, 12, 12, 3)
    target = torch.stack([torch.full((12, 12, 3), 0.25), torch.full((12, 12, 3), 0.75)])
    assert l1_loss(pred, target).item() == pytest.approx(0.5)
    assert l1_loss(pred, target, torch.tensor([1.0, 0.0])).item() == pytest.approx(0.125)
    assert l1_loss(pred, target, torch.tensor([1.0, 0.5])).item() == pytest.approx((0.25 + 0.5 * 0.75) / 2)


def test_weights_are_absolute_not_normalised_in_the_batch():
    """A generated image (alpha = 0.5) counts half a real one also when it is alone in its batch: normalising by
    the batch's weights made alpha a no-op at batch size 1 (the sparse regimes' CPU budget)."""
    pred, target = torch.zeros(1, 12, 12, 3), torch.full((1, 12, 12, 3), 0.5)
    real = photometric_loss(pred, target, 0.2, torch.tensor([1.0]))
    generated = photometric_loss(pred, target, 0.2, torch.tensor([0.5]))
    assert generated.item() == pytest.approx(0.5 * real.item(), rel=1e-6)
    assert photometric_loss(pred, target, 0.2).item() == pytest.approx(real.item(), rel=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssim_with_the_kept_window_is_the_librarys_ssim(dtype):
    from pytorch_msssim import ssim

    torch.manual_seed(0)
    a, b = torch.rand(2, 16, 20, 3, dtype=dtype), torch.rand(2, 16, 20, 3, dtype=dtype)
    expected = ssim(a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2), data_range=1.0, size_average=False)
    assert torch.equal(ssim_per_image(a, b), expected)


def test_an_ssim_window_made_during_evaluation_serves_training():
    from pytorch_msssim import ssim

    from diamond_sss.losses.photometric import ssim_window

    ssim_window.cache_clear()
    a, b = torch.rand(1, 12, 12, 2), torch.rand(1, 12, 12, 2, requires_grad=True)
    with torch.inference_mode():
        ssim_per_image(a, b.detach())  # first use: the window is made here and kept
    ssim_per_image(a, b).sum().backward()
    reference = b.detach().clone().requires_grad_(True)  # the library's gradient, with its own window
    ssim(a.permute(0, 3, 1, 2), reference.permute(0, 3, 1, 2), data_range=1.0).backward()
    assert reference.grad.abs().sum() > 0
    torch.testing.assert_close(b.grad, reference.grad)


def test_ssim_identity_and_dissimilarity():
    a, b = _images()
    assert torch.allclose(ssim_per_image(a, a), torch.ones(2), atol=1e-5)
    assert dssim_loss(a, a).abs().item() < 1e-5
    value = dssim_loss(a, b).item()
    assert 0.5 < value <= 2.0


def test_photometric_loss_mixes_and_weights_per_image():
    a, b = _images()
    lam = 0.3
    per_image = [
        (1 - lam) * (a[i] - b[i]).abs().mean() + lam * (1 - ssim_per_image(a[i : i + 1], b[i : i + 1])[0])
        for i in range(2)
    ]
    assert photometric_loss(a, b, lam).item() == pytest.approx(float(sum(per_image) / 2), rel=1e-5)
    weights = torch.tensor([1.0, 0.5])  # a real and a synthetic image (alpha = 0.5)
    expected = (per_image[0] + 0.5 * per_image[1]) / 2
    assert photometric_loss(a, b, lam, weights).item() == pytest.approx(float(expected), rel=1e-5)
    assert photometric_loss(a, b, lam, 2 * weights).item() == pytest.approx(float(2 * expected), rel=1e-5)


def test_rmse_photometric_error_is_what_psnr_measures_with_its_gradient():
    pred = torch.zeros(2, 12, 12, 3)
    target = torch.stack([torch.full((12, 12, 3), 0.1), torch.full((12, 12, 3), 0.01)])
    target[1, :6] = 0.03  # half the pixels off by 0.03, half by 0.01: RMSE sqrt((0.03^2 + 0.01^2) / 2)
    rmse = rmse_per_image(pred, target)
    assert rmse.tolist() == pytest.approx([math.sqrt(0.01 + 1e-8), math.sqrt(5e-4 + 1e-8)], rel=1e-6)  # + eps
    assert (-20 * torch.log10(rmse)).tolist() == pytest.approx([20.0, 33.0103], abs=1e-3)  # the images' PSNR
    a, b = _images(seed=3)
    lam, weights = 0.3, torch.tensor([1.0, 0.5])
    expected = sum(w * ((1 - lam) * ((a[i] - b[i]).square().mean() + 1e-8).sqrt()
                        + lam * (1 - ssim_per_image(a[i : i + 1], b[i : i + 1])[0]))
                   for i, w in enumerate(weights)) / 2
    assert photometric_loss(a, b, lam, weights, "rmse").item() == pytest.approx(float(expected), rel=1e-5)
    with pytest.raises(ValueError, match=r"photometric error must be one of \['l1', 'rmse'\], got 'l2'"):
        photometric_loss(a, b, lam, error="l2")
    small_a, small_b = (x[:, :11, :11].double() for x in _images(seed=4))
    small_a.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: photometric_loss(x, small_b, 0.0, error="rmse"), (small_a,))


def test_photometric_loss_gradient_and_errors():
    a, b = (x[:, :11, :11].double() for x in _images())
    a.requires_grad_(True)
    weights = torch.tensor([1.0, 0.5], dtype=torch.float64)
    # L1 and D-SSIM mixed and weighted: the analytic gradient against central finite differences
    assert torch.autograd.gradcheck(lambda x: photometric_loss(x, b, 0.2, weights), (a,))
    with pytest.raises(ValueError, match="same shape"):
        photometric_loss(a, b[:1], 0.2)
    with pytest.raises(ValueError, match="lambda_dssim"):
        photometric_loss(a, b, 1.5)
    with pytest.raises(ValueError, match="weights"):
        photometric_loss(a, b, 0.2, torch.ones(3))
    with pytest.raises(ValueError, match="at least 11"):
        photometric_loss(torch.zeros(1, 8, 8, 3), torch.zeros(1, 8, 8, 3), 0.2)


# ----------------------------------------------------------------------------- masks


def test_mask_bce_known_values():
    mask = torch.cat([torch.ones(1, 2, 4, 1), torch.zeros(1, 2, 4, 1)], dim=1)
    assert mask_bce_loss(torch.full_like(mask, 0.5), mask).item() == pytest.approx(math.log(2.0), rel=1e-6)
    alpha = torch.where(mask > 0, torch.tensor(0.8), torch.tensor(0.1))
    expected = 0.5 * (-math.log(0.8)) + 0.5 * (-math.log(0.9))
    assert mask_bce_loss(alpha, mask).item() == pytest.approx(expected, rel=1e-6)
    # Saturated opacity on the wrong side is clamped, not infinite.
    value = mask_bce_loss(torch.zeros_like(mask), torch.ones_like(mask), eps=1e-6)
    assert value.item() == pytest.approx(-math.log(1e-6), rel=1e-4)


def test_mask_entropy_known_values_and_gradient():
    assert mask_entropy_loss(torch.full((1, 3, 3, 1), 0.5)).item() == pytest.approx(math.log(2.0), rel=1e-6)
    binary = torch.tensor([0.0, 1.0, 1.0, 0.0]).view(1, 2, 2, 1)
    assert mask_entropy_loss(binary).item() < 1e-4
    alpha = torch.tensor([0.3, 0.7]).view(1, 1, 2, 1).requires_grad_(True)
    mask_entropy_loss(alpha).backward()
    # d/da of -(a log a + (1-a) log(1-a)) / N = log((1-a)/a) / N: pushes towards the nearer of 0 / 1.
    expected = torch.log((1 - alpha.detach()) / alpha.detach()) / 2
    assert torch.allclose(alpha.grad, expected, atol=1e-6)


# ----------------------------------------------------------------------------- smoothness


def test_bilateral_smoothness_known_answers():
    height, width = 6, 8
    cols = torch.arange(width, dtype=torch.float32).view(1, 1, width, 1).expand(1, height, width, 1)
    constant_image = torch.full((1, height, width, 3), 0.4)
    assert bilateral_smoothness_loss(torch.full((1, height, width, 2), 0.7), constant_image).item() == 0.0
    slope = 0.05
    ramp = slope * cols
    assert bilateral_smoothness_loss(ramp, constant_image).item() == pytest.approx(slope, rel=1e-5)
    image_slope = 0.3
    image = (image_slope * cols).expand(1, height, width, 3)
    expected = slope * math.exp(-image_slope)
    assert bilateral_smoothness_loss(ramp, image).item() == pytest.approx(expected, rel=1e-5)


def test_bilateral_smoothness_respects_mask():
    height, width = 6, 8
    gen = torch.Generator().manual_seed(1)
    attribute = torch.rand(1, height, width, 1, generator=gen)
    image = torch.zeros(1, height, width, 3)
    mask = torch.zeros(1, height, width, 1)
    mask[:, :, :4] = 1.0
    attribute_inside = attribute.clone()
    attribute_inside[:, :, :4] = 0.5
    # Only pairs fully inside the mask count: making the inside constant gives exactly zero.
    assert bilateral_smoothness_loss(attribute_inside, image, mask).item() == 0.0
    expected_x = (attribute[:, :, 1:4] - attribute[:, :, 0:3]).abs().mean()
    expected_y = (attribute[:, 1:, :4] - attribute[:, :-1, :4]).abs().mean()
    value = bilateral_smoothness_loss(attribute, image, mask).item()
    assert value == pytest.approx(float(expected_x + expected_y), rel=1e-5)
    empty = bilateral_smoothness_loss(attribute.requires_grad_(True), image, torch.zeros_like(mask))
    empty.backward()
    assert empty.item() == 0.0 and torch.isfinite(attribute.grad).all()


def test_bilateral_smoothness_gradcheck():
    gen = torch.Generator().manual_seed(2)
    attribute = torch.rand(1, 4, 5, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    image = torch.rand(1, 4, 5, 3, generator=gen, dtype=torch.float64)
    mask = (torch.rand(1, 4, 5, 1, generator=gen, dtype=torch.float64) > 0.3).double()
    assert torch.autograd.gradcheck(lambda a: bilateral_smoothness_loss(a, image, mask), (attribute,))


def test_shared_edge_weights_give_the_same_losses_and_gradients_with_fewer_operators():
    """A step's four smoothed attributes share the image's edge weights (edge_weights, as the objective does): bit for
    bit the losses and gradients of each attribute taking them itself, with 3 x 2 x 12 fewer operators dispatched (per
    direction the image's difference, its mean magnitude, the edge weight, the pair mask and its count: 12 operators,
    7 of them kernels on CUDA, once instead of four times)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    from diamond_sss.losses.regularizers import edge_weights

    class Dispatched(TorchDispatchMode):
        count = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.count += 1
            return func(*args, **(kwargs or {}))

    gen = torch.Generator().manual_seed(3)
    image = torch.rand(2, 12, 10, 3, generator=gen)
    mask = (torch.rand(2, 12, 10, 1, generator=gen) > 0.3).float()
    attributes = [torch.rand(2, 12, 10, channels, generator=gen, requires_grad=True) for channels in (3, 1, 1, 1)]

    def losses(shared: bool) -> tuple[int, list[torch.Tensor]]:
        with Dispatched() as counter:
            edges = edge_weights(image, mask, like=attributes[0]) if shared else None
            values = [bilateral_smoothness_loss(a, image, mask, edges) for a in attributes]
        return counter.count, [*values, *torch.autograd.grad(torch.stack(values).sum(), attributes)]

    each, alone = losses(shared=False)
    once, shared = losses(shared=True)
    assert all(torch.equal(a, b) for a, b in zip(alone, shared, strict=True))
    assert each - once == 3 * 2 * 12
    with pytest.raises(ValueError, match=r"edges were made for an image of shape \(2, 12, 10, 3\)"):
        bilateral_smoothness_loss(attributes[0][:1], image[:1], mask[:1], edge_weights(image, mask))


# ----------------------------------------------------------------------------- enhancement and priors


def test_enhancement_target_known_values():
    levels = torch.tensor([0.0, 0.2, 0.5, 1.0]).view(1, 1, 4, 1).expand(1, 1, 4, 3)
    target = enhancement_target(levels)[0, 0, :, 0]
    sw = 1.0 / (1.0 + math.exp(3.0))  # sigmoid(10 (0.2 - 0.5))
    expected_02 = sw * 0.04 + (1.0 - sw) * (1.0 - 0.8**2)
    assert target.tolist() == pytest.approx([0.0, expected_02, 0.5, 1.0], abs=1e-6)
    # Highlights are darkened and shadows brightened.
    bright = enhancement_target(torch.full((1, 1, 1, 3), 0.9))
    dark = enhancement_target(torch.full((1, 1, 1, 3), 0.1))
    assert bright.max() < 0.9 and dark.min() > 0.1


def test_enhancement_and_base_color_losses():
    gen = torch.Generator().manual_seed(3)
    image = torch.rand(2, 5, 5, 3, generator=gen)
    target = enhancement_target(image)
    mask = torch.ones(2, 5, 5, 1)
    assert enhancement_loss(target, image, mask).item() == pytest.approx(0.0, abs=1e-7)
    shifted = (target + 0.1).requires_grad_(True)
    loss = enhancement_loss(shifted, image, mask)
    assert loss.item() == pytest.approx(0.1, rel=1e-5)
    loss.backward()
    assert torch.isfinite(shifted.grad).all()
    half = torch.zeros(2, 5, 5, 1)
    half[:, :2] = 1.0
    base = image.clone()
    base[:, :2] += 0.2
    base[:, 2:] += 0.5
    assert base_color_prior_loss(base, image, half).item() == pytest.approx(0.2, rel=1e-5)
    assert base_color_prior_loss(base, image).item() == pytest.approx((2 * 0.2 + 3 * 0.5) / 5, rel=1e-5)


def test_incident_and_raytrace_losses():
    incident = torch.tensor([1.5, -0.2, 0.4])
    visibility = torch.tensor([0.75, 0.1, 0.4])
    assert incident_light_loss(incident, visibility).item() == pytest.approx((0.25 + 0.1 + 0.0) / 3)
    mask = torch.tensor([1.0, 0.0, 0.0])
    assert incident_light_loss(incident, visibility, mask).item() == pytest.approx(0.25)
    v_sh = torch.tensor([0.2, 0.9], requires_grad=True)
    v_rt = torch.tensor([0.5, 0.5], requires_grad=True)
    loss = raytrace_visibility_loss(v_sh, v_rt)
    assert loss.item() == pytest.approx(0.35)
    loss.backward()
    assert v_sh.grad.tolist() == pytest.approx([-0.5, 0.5]) and v_rt.grad is None
    with pytest.raises(ValueError, match="must match"):
        incident_light_loss(incident, visibility[:2])


# ----------------------------------------------------------------------------- normals


def _camera(eye, target, size: int = 16):
    c2w = look_at_opengl_c2w(torch.tensor(eye), torch.tensor(target))
    w2c = opengl_c2w_to_opencv_w2c(c2w).to(torch.float32)
    return w2c, intrinsics_from_fov(math.radians(50.0), size, size)


def _plane_depth(w2c, K, size: int, normal, offset: float) -> torch.Tensor:
    """Depth of the plane ``n . X = offset``: ``D = (offset - n . C) / (n . w)``, ``w`` the ray at z = 1."""
    uv = pixel_grid(size, size).reshape(-1, 2)
    center = camera_centers(w2c)
    rays = unproject_pixels(uv, torch.ones(uv.shape[0]), w2c, K) - center
    depth = (offset - normal @ center) / (rays @ normal)
    return depth.reshape(1, size, size, 1)


@pytest.mark.parametrize(
    ("eye", "normal", "offset"),
    [((0.3, -0.4, 3.0), (0.0, 0.0, 1.0), 0.0), ((2.0, 1.0, 2.5), (0.3, -0.2, 1.0), 0.2)],
)
def test_normals_from_planar_depth_are_exact(eye, normal, offset):
    size = 16
    w2c, K = _camera(eye, (0.0, 0.0, 0.0), size)
    n = torch.tensor(normal)
    n = n / n.norm()
    depth = _plane_depth(w2c, K, size, n, offset)
    normals = normals_from_depth(depth, w2c, K)
    assert normals.shape == (1, size, size, 3)
    # The camera is on the +n side of the plane, so the camera-facing normal is +n everywhere.
    assert torch.allclose(normals, n.expand_as(normals), atol=1e-4)


def test_normals_from_depth_faces_the_camera_and_batches():
    size = 8
    w2c, K = _camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), size)
    depth = torch.full((2, size, size, 1), 2.0)
    normals = normals_from_depth(depth, torch.stack([w2c, w2c]), K)
    assert torch.allclose(normals, torch.tensor([0.0, 0.0, 1.0]).expand_as(normals), atol=1e-5)
    with pytest.raises(ValueError, match="w2c"):
        normals_from_depth(depth, torch.eye(3), K)


def test_normals_from_depth_gradcheck():
    size = 5
    w2c, K = _camera((0.5, 0.2, 3.0), (0.0, 0.0, 0.0), size)
    gen = torch.Generator().manual_seed(4)
    depth = (3.0 + 0.1 * torch.rand(1, size, size, 1, generator=gen, dtype=torch.float64)).requires_grad_(
        True
    )
    reference = torch.rand(1, size, size, 3, generator=gen, dtype=torch.float64)

    def objective(d):
        return (normals_from_depth(d, w2c.double(), K.double()) * reference).sum()

    assert torch.autograd.gradcheck(objective, (depth,))


def test_normal_consistency_known_values():
    normals = torch.tensor([0.0, 0.0, 1.0]).expand(1, 2, 2, 3).clone().requires_grad_(True)
    pseudo = torch.tensor([1.0, 0.0, 0.0]).expand(1, 2, 2, 3)
    assert normal_consistency_loss(normals, pseudo).item() == pytest.approx(math.sqrt(2.0), rel=1e-6)
    mask = torch.tensor([1.0, 0.0, 0.0, 0.0]).view(1, 2, 2, 1)
    mixed = pseudo.clone()
    mixed[0, 0, 1] = torch.tensor([0.0, 0.0, 1.0])
    assert normal_consistency_loss(normals, mixed, mask).item() == pytest.approx(math.sqrt(2.0), rel=1e-6)
    loss = normal_consistency_loss(normals, normals.detach())
    loss.backward()
    assert loss.item() == 0.0 and torch.isfinite(normals.grad).all()


# ----------------------------------------------------------------------------- LPIPS


def _random_lpips_weights(seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    weights = {}
    for key, shape in expected_shapes().items():
        if key.startswith("lin."):
            weights[key] = torch.rand(shape, generator=gen)
        elif key.endswith(".bias"):
            weights[key] = 0.01 * torch.randn(shape, generator=gen)
        else:
            fan_in = shape[1] * shape[2] * shape[3]
            weights[key] = torch.randn(shape, generator=gen) * math.sqrt(2.0 / fan_in)
    return weights


@pytest.fixture
def fresh_lpips_warning(monkeypatch):
    reset_warnings()
    monkeypatch.delenv(lpips_module.WEIGHTS_ENV_VAR, raising=False)


def test_lpips_loads_and_measures(tmp_path, fresh_lpips_warning, monkeypatch):
    path = tmp_path / "lpips_vgg.safetensors"
    save_file(_random_lpips_weights(), str(path))
    model = load_lpips(str(path))
    assert isinstance(model, LPIPS)
    assert not any(p.requires_grad for p in model.parameters())
    a, b = _images(batch=3, size=32, seed=5)
    distance = model(a, b)
    assert distance.shape == (3,)
    assert (distance > 0).all()
    assert torch.allclose(model(a, a), torch.zeros(3), atol=1e-6)
    # Gradients flow to the prediction (LPIPS is used as a loss).
    pred = a.clone().requires_grad_(True)
    model(pred, b).sum().backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0
    monkeypatch.setenv(lpips_module.WEIGHTS_ENV_VAR, str(path))
    from_env = load_lpips(None)
    assert from_env is not None and torch.allclose(from_env(a, b), distance)


def test_lpips_first_layer_matches_a_direct_computation(tmp_path, fresh_lpips_warning):
    weights = _random_lpips_weights(seed=8)
    for index in range(1, len(LIN_CHANNELS)):
        weights[f"lin.{index}.weight"].zero_()
    weights["lin.0.weight"].fill_(1.0)
    path = tmp_path / "first_layer.safetensors"
    save_file(weights, str(path))
    model = load_lpips(str(path))
    a, b = _images(batch=2, size=16, seed=9)
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def relu1_2(image):
        x = ((image.permute(0, 3, 1, 2) * 2 - 1) - shift) / scale
        x = torch.relu(
            torch.nn.functional.conv2d(
                x, weights["vgg.conv1_1.weight"], weights["vgg.conv1_1.bias"], padding=1
            )
        )
        x = torch.relu(
            torch.nn.functional.conv2d(
                x, weights["vgg.conv1_2.weight"], weights["vgg.conv1_2.bias"], padding=1
            )
        )
        return x / (x.norm(dim=1, keepdim=True) + 1e-10)

    expected = (relu1_2(a) - relu1_2(b)).square().sum(1).mean(dim=(1, 2))
    assert torch.allclose(model(a, b), expected, rtol=1e-4, atol=1e-6)


def test_lpips_missing_weights_warns_once(tmp_path, fresh_lpips_warning, caplog):
    assert load_lpips(None) is None
    assert load_lpips(str(tmp_path / "absent.safetensors")) is None
    assert load_lpips(None) is None
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warned == ["LPIPS is disabled: no weights file given and $DIAMOND_SSS_LPIPS_WEIGHTS is not set"]


def test_lpips_wrong_keys_name_file_and_key(tmp_path, fresh_lpips_warning):
    weights = _random_lpips_weights()
    weights["lin.5.weight"] = torch.rand(1, 8, 1, 1)
    extra = tmp_path / "extra.safetensors"
    save_file(weights, str(extra))
    with pytest.raises(ValueError, match=r"extra\.safetensors.*'lin\.5\.weight'"):
        load_lpips(str(extra))
    weights = _random_lpips_weights()
    del weights["vgg.conv4_2.bias"]
    missing = tmp_path / "missing.safetensors"
    save_file(weights, str(missing))
    with pytest.raises(ValueError, match=r"missing\.safetensors.*'vgg\.conv4_2\.bias'"):
        load_lpips(str(missing))
    weights = _random_lpips_weights()
    weights["lin.2.weight"] = torch.rand(1, 128, 1, 1)
    misshaped = tmp_path / "misshaped.safetensors"
    save_file(weights, str(misshaped))
    with pytest.raises(ValueError, match=r"misshaped\.safetensors.*'lin\.2\.weight'"):
        load_lpips(str(misshaped))


@pytest.mark.parametrize("layout", ["torchvision", "lpips"])
def test_convert_official_state_dicts(layout):
    gen = torch.Generator().manual_seed(6)
    vgg_sd = {"classifier.0.weight": torch.randn(4, 4, generator=gen)}
    slice_of = {0: 1, 2: 1, 5: 2, 7: 2, 10: 3, 12: 3, 14: 3, 17: 4, 19: 4, 21: 4, 24: 5, 26: 5, 28: 5}
    for _, c_in, c_out, index in VGG16_CONVS:
        prefix = f"features.{index}" if layout == "torchvision" else f"net.slice{slice_of[index]}.{index}"
        vgg_sd[f"{prefix}.weight"] = torch.randn(c_out, c_in, 3, 3, generator=gen)
        vgg_sd[f"{prefix}.bias"] = torch.randn(c_out, generator=gen)
    lin_sd = {
        f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=gen) for i, c in enumerate(LIN_CHANNELS)
    }
    converted = convert_lpips_state_dict(vgg_sd, lin_sd)
    assert set(converted) == set(expected_shapes())
    first = "features.14" if layout == "torchvision" else "net.slice3.14"
    assert torch.equal(converted["vgg.conv3_3.weight"], vgg_sd[f"{first}.weight"])
    assert torch.equal(converted["lin.4.weight"], lin_sd["lin4.model.1.weight"])
    LPIPS().load_state_dict(converted, strict=True)
    del vgg_sd[f"{first}.bias"]
    with pytest.raises(KeyError, match="14.bias"):
        convert_lpips_state_dict(vgg_sd, lin_sd)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_matches_cpu(tmp_path, fresh_lpips_warning):
    path = tmp_path / "lpips_vgg.safetensors"
    save_file(_random_lpips_weights(), str(path))
    model = load_lpips(str(path))
    a, b = _images(batch=2, size=32, seed=7)
    mask = (a[..., :1] > 0.3).float()
    cpu = [photometric_loss(a, b, 0.3), photometric_loss(a, b, 0.3, error="rmse"),
           bilateral_smoothness_loss(a, b, mask), model(a, b)]
    a, b, mask = a.cuda(), b.cuda(), mask.cuda()
    model = model.cuda()
    cuda = [photometric_loss(a, b, 0.3), photometric_loss(a, b, 0.3, error="rmse"),
            bilateral_smoothness_loss(a, b, mask), model(a, b)]
    for expected, value in zip(cpu, cuda):
        assert value.device.type == "cuda"
        assert torch.allclose(value.cpu(), expected, rtol=1e-4, atol=1e-5)
