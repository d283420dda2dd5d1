"""Tests of the Gaussian rasterization layer (CPU path; CUDA parity tests run only with a GPU)."""

from __future__ import annotations

import math
import os
import tempfile

import pytest
import torch

from diamond_sss.rendering import RasterOutput, project_gaussians, quat_to_rotmat, rasterize

os.environ.setdefault("TORCH_EXTENSIONS_DIR", os.path.join(tempfile.gettempdir(), "diamond_sss_torch_ext"))

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def _camera(width: int, height: int, focal: float, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Identity w2c (camera at the origin looking down +z) and a pinhole K with the centre on a pixel centre."""
    viewmats = torch.eye(4, dtype=dtype)[None]
    Ks = torch.tensor(
        [[focal, 0.0, width / 2 + 0.5], [0.0, focal, height / 2 + 0.5], [0.0, 0.0, 1.0]], dtype=dtype
    )
    return viewmats, Ks[None]


def _random_scene(n: int, n_cameras: int, channels: int, seed: int, dtype=torch.float32, device="cpu"):
    """Gaussians around the origin seen by cameras on a circle at distance 4, looking at the origin."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 1.6
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.15 + 0.02
    opacities = torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05
    features = torch.rand(n, channels, generator=g, dtype=dtype)
    viewmats = []
    for k in range(n_cameras):
        angle = 2 * math.pi * k / n_cameras + 0.3
        eye = torch.tensor([4 * math.sin(angle), 0.5, -4 * math.cos(angle)], dtype=torch.float64)
        forward = -eye / eye.norm()
        right = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), forward)
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        rot = torch.stack([right, down, forward])
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = rot
        w2c[:3, 3] = -rot @ eye
        viewmats.append(w2c)
    viewmats = torch.stack(viewmats).to(dtype)
    Ks = torch.tensor([[60.0, 0.0, 28.0], [0.0, 60.0, 20.0], [0.0, 0.0, 1.0]], dtype=dtype).expand(
        n_cameras, 3, 3
    )
    tensors = (means, quats, scales, opacities, features, viewmats, Ks.contiguous())
    return tuple(t.to(device) for t in tensors)


def _reference_render(means, quats, scales, opacities, features, viewmats, Ks, width, height):
    """Untiled brute-force compositing of every (pixel, Gaussian) pair, following gsplat's per-pixel loop."""
    proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height)
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    pixels = torch.stack([u, v], dim=-1).reshape(-1, 2).to(means.dtype)
    outputs = []
    for cam in range(viewmats.shape[0]):
        ids = torch.nonzero((proj.radii[cam] > 0).all(-1)).squeeze(-1)
        ids = ids[torch.sort(proj.depths[cam, ids], stable=True).indices]
        feats = features if features.ndim == 2 else features[cam]
        feats = torch.cat([feats[ids], proj.depths[cam, ids, None]], dim=-1)
        d = pixels[:, None, :] - proj.means2d[cam, ids][None]
        a, b, c = proj.conics[cam, ids].unbind(-1)
        q = a * d[..., 0] ** 2 + 2 * b * d[..., 0] * d[..., 1] + c * d[..., 1] ** 2
        alpha = (opacities[ids] * torch.exp(-0.5 * q)).clamp_max(0.999)
        alpha = torch.where(alpha >= 1 / 255, alpha, 0.0)
        transmit = torch.cumprod(1 - alpha, dim=-1)
        t_excl = torch.cat([torch.ones_like(transmit[:, :1]), transmit[:, :-1]], dim=-1)
        weights = torch.where(transmit > 1e-4, alpha * t_excl, 0.0)
        rendered = weights @ feats
        acc = weights.sum(-1, keepdim=True)
        outputs.append(torch.cat([rendered[:, :-1], rendered[:, -1:] / acc.clamp_min(1e-10), acc], -1))
    out = torch.stack(outputs).reshape(viewmats.shape[0], height, width, -1)
    return out[..., :-2], out[..., -2:-1], out[..., -1:]


def _single_gaussian(mean, scale, opacity, feature, dtype=torch.float32):
    means = torch.tensor([mean], dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype)
    scales = torch.full((1, 3), scale, dtype=dtype)
    opacities = torch.tensor([opacity], dtype=dtype)
    features = torch.tensor([feature], dtype=dtype)
    return means, quats, scales, opacities, features


def test_single_isotropic_gaussian_known_answer():
    width, height, focal, z, scale, opacity = 40, 36, 50.0, 2.5, 0.08, 0.7
    viewmats, Ks = _camera(width, height, focal)
    means, quats, scales, opacities, features = _single_gaussian(
        [0.0, 0.0, z], scale, opacity, [0.2, 0.5, 0.9]
    )
    out = rasterize(means, quats, scales, opacities, features, viewmats, Ks, width, height, backend="cpu")
    assert isinstance(out, RasterOutput)
    assert out.features.shape == (1, height, width, 3)
    assert out.depth.shape == out.alpha.shape == (1, height, width, 1)

    var2d = (focal * scale / z) ** 2 + 0.3
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    d2 = (u - (width / 2 + 0.5)) ** 2 + (v - (height / 2 + 0.5)) ** 2
    expected = opacity * torch.exp(-0.5 * d2 / var2d)
    expected = torch.where(expected >= 1 / 255, expected, 0.0)
    alpha = out.alpha[0, ..., 0]
    torch.testing.assert_close(alpha, expected, atol=1e-5, rtol=1e-4)
    assert alpha[height // 2, width // 2] == pytest.approx(opacity, abs=1e-6)
    covered = alpha > 0
    assert covered.sum() > 20
    torch.testing.assert_close(
        out.depth[0, covered, 0], torch.full((int(covered.sum()),), z), rtol=1e-5, atol=0
    )
    torch.testing.assert_close(
        out.features[0][covered] / alpha[covered, None], features.expand(int(covered.sum()), 3)
    )
    assert (out.depth[0, ~covered] == 0).all() and (out.features[0, ~covered] == 0).all()


def test_two_overlapping_gaussians_front_to_back():
    width, height, focal = 32, 32, 40.0
    viewmats, Ks = _camera(width, height, focal)
    means = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 2.0]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.5, 0.1, -0.2, 0.3]])
    scales = torch.tensor([[0.1, 0.1, 0.1], [0.05, 0.05, 0.05]])
    opacities = torch.tensor([0.6, 0.5])
    features = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    out = rasterize(means, quats, scales, opacities, features, viewmats, Ks, width, height, backend="cpu")
    centre = (0, height // 2, width // 2)
    a_back, a_front = 0.6, 0.5  # at the common centre every Gaussian's alpha is its opacity
    alpha = 1 - (1 - a_front) * (1 - a_back)
    assert out.alpha[centre].item() == pytest.approx(alpha, abs=1e-6)
    torch.testing.assert_close(out.features[centre], torch.tensor([a_back * (1 - a_front), a_front]))
    expected_depth = (a_front * 2.0 + a_back * (1 - a_front) * 3.0) / alpha
    assert out.depth[centre].item() == pytest.approx(expected_depth, rel=1e-6)

    order = torch.tensor([1, 0])
    swapped = rasterize(
        means[order],
        quats[order],
        scales[order],
        opacities[order],
        features[order],
        viewmats,
        Ks,
        width,
        height,
    )
    torch.testing.assert_close(swapped.features, out.features)
    torch.testing.assert_close(swapped.alpha, out.alpha)


def test_alpha_clamp_and_cutoff():
    width, height, focal, z, scale = 48, 48, 40.0, 2.0, 0.1
    viewmats, Ks = _camera(width, height, focal)
    means, quats, scales, opacities, features = _single_gaussian([0.0, 0.0, z], scale, 0.99999, [1.0])
    out = rasterize(means, quats, scales, opacities, features, viewmats, Ks, width, height, backend="cpu")
    alpha = out.alpha[0, height // 2, :, 0]
    assert alpha[width // 2].item() == pytest.approx(0.999, abs=1e-6)

    var2d = (focal * scale / z) ** 2 + 0.3
    offsets = torch.arange(width) + 0.5 - (width / 2 + 0.5)
    raw = 0.99999 * torch.exp(-0.5 * offsets**2 / var2d)
    below = raw < 1 / 255
    assert below.any() and (raw[~below] < 0.999).any()
    assert (alpha[below] == 0).all()
    torch.testing.assert_close(alpha[~below], raw[~below].clamp_max(0.999), atol=1e-6, rtol=1e-5)


def test_early_termination_at_low_transmittance():
    width, height, focal = 16, 16, 20.0
    viewmats, Ks = _camera(width, height, focal)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 4.0]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(3, 4)
    scales = torch.full((3, 3), 0.2)
    opacities = torch.tensor([0.99999, 0.99999, 0.5])
    features = torch.tensor([[1.0], [10.0], [100.0]])
    out = rasterize(means, quats, scales, opacities, features, viewmats, Ks, width, height, backend="cpu")
    # After the first Gaussian T = 1e-3; the second would bring it to 1e-6 <= 1e-4, so compositing stops.
    centre = (0, height // 2, width // 2, 0)
    assert out.features[centre].item() == pytest.approx(0.999, abs=1e-6)
    assert out.alpha[centre].item() == pytest.approx(0.999, abs=1e-6)
    assert out.depth[centre].item() == pytest.approx(2.0, abs=1e-5)


@pytest.mark.parametrize("z", [-2.0, 0.005])
def test_culling_behind_camera_and_near_plane(z):
    viewmats, Ks = _camera(16, 16, 20.0)
    means, quats, scales, opacities, features = _single_gaussian([0.0, 0.0, z], 0.5, 0.9, [1.0, 1.0])
    means.requires_grad_(True)
    out = rasterize(means, quats, scales, opacities, features, viewmats, Ks, 16, 16, backend="cpu")
    assert (out.alpha == 0).all() and (out.features == 0).all() and (out.depth == 0).all()
    assert (out.info["radii"] == 0).all()
    out.info["means2d"].retain_grad()
    (out.features.sum() + out.alpha.sum()).backward()  # still differentiable, with zero gradients
    assert (means.grad == 0).all() and (out.info["means2d"].grad == 0).all()


def test_culling_outside_image():
    viewmats, Ks = _camera(16, 16, 20.0)
    means, quats, scales, opacities, features = _single_gaussian([3.0, 0.0, 2.0], 0.05, 0.9, [1.0])
    out = rasterize(means, quats, scales, opacities, features, viewmats, Ks, 16, 16, backend="cpu")
    assert (out.info["radii"] == 0).all() and (out.alpha == 0).all()


@pytest.mark.parametrize("tile_size", [16, 8])
def test_tiled_matches_untiled_reference(tile_size):
    scene = _random_scene(n=60, n_cameras=3, channels=4, seed=1)
    width, height = 56, 40
    out = rasterize(*scene, width, height, backend="cpu", tile_size=tile_size)
    ref_features, ref_depth, ref_alpha = _reference_render(*scene, width, height)
    assert out.alpha.max() > 0.5 and (out.alpha > 0).float().mean() > 0.3
    torch.testing.assert_close(out.features, ref_features, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(out.alpha, ref_alpha, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(out.depth, ref_depth, atol=2e-4, rtol=1e-4)


def test_gaussian_straddling_tiles_renders_continuously():
    width = height = 32
    viewmats, Ks = _camera(width, height, 40.0)
    Ks[0, 0, 2] = Ks[0, 1, 2] = 16.0  # the centre projects onto the corner shared by four 16x16 tiles
    means, quats, scales, opacities, features = _single_gaussian([0.0, 0.0, 2.0], 0.15, 0.8, [1.0])
    tiled = rasterize(means, quats, scales, opacities, features, viewmats, Ks, width, height, tile_size=16)
    single = rasterize(means, quats, scales, opacities, features, viewmats, Ks, width, height, tile_size=32)
    torch.testing.assert_close(tiled.alpha, single.alpha, atol=1e-6, rtol=1e-6)
    alpha = tiled.alpha[0, ..., 0]
    # Symmetric about the tile corner: mirrored pixels across both tile boundaries are equal and non-zero.
    torch.testing.assert_close(alpha, alpha.flip(0).flip(1), atol=1e-6, rtol=1e-5)
    assert alpha[15, 15] > 0.5 and alpha[15, 15] == pytest.approx(alpha[16, 16].item(), abs=1e-6)
    assert tiled.info["tiles_per_gauss"].tolist() == [[4]]  # [cameras, Gaussians]


def test_per_camera_features_match_single_camera_renders():
    means, quats, scales, opacities, features, viewmats, Ks = _random_scene(30, 2, 3, seed=2)
    per_camera = torch.stack([features, features.flip(-1)])
    out = rasterize(means, quats, scales, opacities, per_camera, viewmats, Ks, 40, 32, backend="cpu")
    for cam in range(2):
        single = rasterize(means, quats, scales, opacities, per_camera[cam], viewmats[cam : cam + 1],
                           Ks[cam : cam + 1], 40, 32)  # fmt: skip
        torch.testing.assert_close(out.features[cam], single.features[0])
        torch.testing.assert_close(out.depth[cam], single.depth[0])


def test_gradcheck_float64():
    means = torch.tensor(
        [[0.1, -0.1, 2.0], [-0.2, 0.15, 2.4], [0.05, 0.2, 2.8], [0.2, 0.1, 3.1]], dtype=torch.float64
    )
    g = torch.Generator().manual_seed(1)
    quats = torch.randn(4, 4, generator=g, dtype=torch.float64)
    scales = torch.tensor(
        [[0.625, 0.375, 0.5], [0.5, 0.75, 0.375], [0.625, 0.5, 0.75], [0.75, 0.5, 0.625]], dtype=torch.float64
    )
    opacities = torch.tensor([0.45, 0.6, 0.5, 0.7], dtype=torch.float64)
    features = torch.rand(4, 2, generator=g, dtype=torch.float64)
    viewmats, Ks = _camera(8, 8, 10.0, dtype=torch.float64)

    def render(means, quats, scales, opacities, features):
        out = rasterize(
            means, quats, scales, opacities, features, viewmats, Ks, 8, 8, backend="cpu", tile_size=4
        )
        return out.features, out.depth, out.alpha

    with torch.no_grad():
        proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, 8, 8)
        v, u = torch.meshgrid(torch.arange(8) + 0.5, torch.arange(8) + 0.5, indexing="ij")
        d = torch.stack([u, v], -1).reshape(-1, 1, 2).double() - proj.means2d[0]
        a, b, c = proj.conics[0].unbind(-1)
        alpha = opacities * torch.exp(
            -0.5 * (a * d[..., 0] ** 2 + 2 * b * d[..., 0] * d[..., 1] + c * d[..., 1] ** 2)
        )
        near_cutoff = (alpha > 0.8 / 255) & (alpha < 1.25 / 255)
        assert not near_cutoff.any() and alpha.max() < 0.99  # away from the non-smooth cut-off and clamp
        assert (alpha < 0.8 / 255).any() and (alpha > 1.25 / 255).sum() > 200
    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, features))
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_means2d_gradient_and_absgrad():
    scene = _random_scene(40, 2, 3, seed=4)
    means = scene[0].clone().requires_grad_(True)
    out = rasterize(means, *scene[1:], 56, 40, backend="cpu", absgrad=True)
    means2d = out.info["means2d"]
    assert means2d.shape == (2, 40, 2)
    means2d.retain_grad()
    weights = torch.rand(out.features.shape, generator=torch.Generator().manual_seed(0))
    (out.features * weights).sum().backward()
    visible = (out.info["radii"] > 0).all(-1)
    grad, absgrad = means2d.grad, means2d.absgrad
    assert grad[visible].abs().sum() > 0 and (grad[~visible] == 0).all()
    assert absgrad.shape == grad.shape and (absgrad[~visible] == 0).all()
    assert (absgrad >= grad.abs() - 1e-6).all() and (absgrad[visible].sum() > grad[visible].abs().sum())


def test_means2d_gradient_is_pixel_space_gradient():
    """Moving the principal point by ``du`` translates every projected mean by ``du`` pixels, so the finite
    difference of the loss along ``cx`` equals the sum of the ``info["means2d"]`` gradients along ``u``."""
    scene = _random_scene(30, 1, 3, seed=9, dtype=torch.float64)
    scene[0].requires_grad_(True)
    weights = torch.rand(1, 40, 56, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)

    def loss(Ks):
        out = rasterize(*scene[:6], Ks, 56, 40, backend="cpu")
        return (out.features * weights).sum(), out.info["means2d"]

    value, means2d = loss(scene[6])
    means2d.retain_grad()
    value.backward()
    step = torch.zeros_like(scene[6])
    for axis, (row, col) in enumerate([(0, 2), (1, 2)]):
        step.zero_()
        step[0, row, col] = 1e-5
        numeric = (loss(scene[6] + step)[0] - loss(scene[6] - step)[0]) / 2e-5
        assert means2d.grad[..., axis].sum().item() == pytest.approx(numeric.item(), rel=1e-5, abs=1e-8)


def test_packed_matches_unpacked():
    scene = _random_scene(40, 2, 3, seed=10)
    scene[0].requires_grad_(True)
    results = []
    for packed in (False, True):
        out = rasterize(*scene, 56, 40, backend="cpu", packed=packed)
        out.info["means2d"].retain_grad()
        out.features.sum().backward()
        results.append(out)
    dense, packed = results
    torch.testing.assert_close(dense.features, packed.features, atol=0, rtol=0)
    cams, ids = packed.info["camera_ids"], packed.info["gaussian_ids"]
    assert len(ids) == int((dense.info["radii"] > 0).all(-1).sum())
    torch.testing.assert_close(dense.info["radii"][cams, ids], packed.info["radii"])
    torch.testing.assert_close(dense.info["means2d"].grad[cams, ids], packed.info["means2d"].grad)


@pytest.mark.parametrize(("packed", "absgrad"), [(False, False), (True, False), (True, True)])
def test_default_strategy_runs_on_cpu(packed, absgrad):
    from gsplat.strategy import DefaultStrategy

    means, quats, scales, opacities, features, viewmats, Ks = _random_scene(50, 2, 3, seed=5)
    params = torch.nn.ParameterDict(
        {
            "means": means,
            "quats": quats,
            "scales": torch.log(scales),
            "opacities": torch.logit(opacities),
            "colors": features,
        }
    )
    optimizers = {name: torch.optim.Adam([p], lr=1e-3) for name, p in params.items()}
    strategy = DefaultStrategy(
        refine_start_iter=1, refine_every=2, grow_grad2d=1e-8, reset_every=1000, absgrad=absgrad
    )
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    target = torch.rand(2, 40, 56, 3, generator=torch.Generator().manual_seed(1))
    counts = []
    for step in range(3):
        out = rasterize(
            params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
            params["colors"], viewmats, Ks, 56, 40, backend="cpu", packed=packed, absgrad=absgrad,
        )  # fmt: skip
        strategy.step_pre_backward(params, optimizers, state, step, out.info)
        ((out.features - target) ** 2).mean().backward()
        strategy.step_post_backward(params, optimizers, state, step, out.info, packed=packed)
        if step < 2:
            counts.append(state["count"].clone())
            grad2d = state["grad2d"].clone()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad()
    assert counts[0].max() == 2 and counts[1].max() == 4  # two cameras per step
    assert (counts[1] >= counts[0]).all() and (grad2d > 0).sum() > 10
    assert len(params["means"]) > 50  # step 2 refines: high-gradient Gaussians were duplicated or split


def test_quat_to_rotmat_known_rotation():
    half = math.pi / 4  # 90 degrees about z, given unnormalised
    rot = quat_to_rotmat(torch.tensor([[3 * math.cos(half), 0.0, 0.0, 3 * math.sin(half)]]))[0]
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    torch.testing.assert_close(rot, expected, atol=1e-6, rtol=0)


def test_invalid_inputs_raise():
    means, quats, scales, opacities, features, viewmats, Ks = _random_scene(5, 1, 3, seed=6)
    with pytest.raises(ValueError, match="quats"):
        rasterize(means, quats[:, :3], scales, opacities, features, viewmats, Ks, 8, 8)
    with pytest.raises(ValueError, match="features"):
        rasterize(means, quats, scales, opacities, features[:4], viewmats, Ks, 8, 8)
    with pytest.raises(TypeError, match="dtype"):
        rasterize(means, quats, scales, opacities, features.double(), viewmats, Ks, 8, 8)
    with pytest.raises(ValueError, match="backend"):
        rasterize(means, quats, scales, opacities, features, viewmats, Ks, 8, 8, backend="opengl")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA"):
            rasterize(means, quats, scales, opacities, features, viewmats, Ks, 8, 8, backend="cuda")


def _outputs_and_gradients(scene, device: str):
    """Forward outputs, radii, screen-space and input gradients of ``rasterize`` on ``device`` (on the CPU).

    Inputs are fresh leaves on ``device`` (``detach().to()``), so each run owns its gradients.
    """
    inputs = [t.detach().to(device).requires_grad_(i < 5) for i, t in enumerate(scene)]
    out = rasterize(*inputs, 56, 40)
    assert out.info["backend"] == device
    out.info["means2d"].retain_grad()
    loss = (out.features * torch.linspace(0, 1, 5, device=device)).sum() + (out.depth * out.alpha).sum()
    loss.backward()
    grads = [t.grad.cpu() for t in inputs[:5]]
    return (out.features.detach().cpu(), out.depth.detach().cpu(), out.alpha.detach().cpu(),
            out.info["radii"].cpu(), out.info["means2d"].grad.cpu(), grads)  # fmt: skip


def _parity_scene(per_camera: bool):
    scene = _random_scene(200, 3, 5, seed=7)
    if per_camera:
        scene = scene[:4] + (torch.rand(3, 200, 5, generator=torch.Generator().manual_seed(8)),) + scene[5:]
    return scene


@pytest.mark.parametrize("per_camera", [False, True])
def test_cpu_runs_are_identical(per_camera):
    """The parity harness on CPU twice: bit-identical outputs and gradients (and the harness itself works)."""
    scene = _parity_scene(per_camera)
    first, second = _outputs_and_gradients(scene, "cpu"), _outputs_and_gradients(scene, "cpu")
    for a, b in zip(first[:5] + tuple(first[5]), second[:5] + tuple(second[5])):
        assert torch.equal(a, b)
    assert all(t.grad is None for t in scene)


@cuda
@pytest.mark.cuda
@pytest.mark.parametrize("per_camera", [False, True])
def test_cpu_cuda_parity(per_camera):
    scene = _parity_scene(per_camera)
    cpu, gpu = _outputs_and_gradients(scene, "cpu"), _outputs_and_gradients(scene, "cuda")
    for a, b in zip(cpu[:3], gpu[:3]):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-3)
    assert (cpu[3] != gpu[3]).float().mean() < 0.01  # radii: ceil() may differ where float32 rounding does
    torch.testing.assert_close(cpu[4], gpu[4], atol=1e-4, rtol=1e-2)
    for a, b in zip(cpu[5], gpu[5]):
        torch.testing.assert_close(a, b, atol=1e-3, rtol=1e-2)
