from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diamond_sss.data.conventions import look_at_opengl_c2w, opengl_c2w_to_opencv_w2c
from diamond_sss.shading import (
    GBUFFER_FEATURE_DIM,
    GBUFFER_FEATURES,
    GBuffer,
    SSSMLPConfig,
    SSSResidualMLP,
    deferred_shade,
    eval_sh,
    fresnel_schlick_ue4,
    geometry_smith,
    ggx_distribution,
    light_geometry,
    light_sh_encoding,
    pbr_shade,
    positional_encoding,
    sh_basis,
    smith_g1,
    visibility_from_sh,
)
from diamond_sss.shading.deferred import LIGHT_FALLOFFS
from diamond_sss.training.overrides import CHOICES, make_config


def sphere_quadrature(
    num_mu: int = 24, num_phi: int = 48, upper_hemisphere: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Legendre in cos(theta) x uniform phi: exact for spherical polynomials of degree < 2 num_mu."""
    mu, w_mu = np.polynomial.legendre.leggauss(num_mu)
    if upper_hemisphere:
        mu, w_mu = 0.5 * (mu + 1.0), 0.5 * w_mu
    phi = (np.arange(num_phi) + 0.5) * 2 * np.pi / num_phi
    mu_g, phi_g = np.meshgrid(mu, phi, indexing="ij")
    sin = np.sqrt(1 - mu_g**2)
    dirs = np.stack([sin * np.cos(phi_g), sin * np.sin(phi_g), mu_g], -1).reshape(-1, 3)
    weights = (w_mu[:, None] * np.full(num_phi, 2 * np.pi / num_phi)[None, :]).reshape(-1)
    return torch.from_numpy(dirs), torch.from_numpy(weights)


# ----------------------------------------------------------------------------- spherical harmonics


def test_sh_basis_closed_form_on_axes():
    dirs = torch.eye(3, dtype=torch.float64)  # +x, +y, +z
    basis = sh_basis(dirs, 3)
    y00 = 0.5 / math.sqrt(math.pi)
    y1 = math.sqrt(3 / (4 * math.pi))
    y20_z = 0.5 * math.sqrt(5 / math.pi)  # Y_2^0 = 1/4 sqrt(5/pi) (3 z^2 - 1) at z = 1
    y22_x = 0.25 * math.sqrt(15 / math.pi)  # Y_2^2 = 1/4 sqrt(15/pi) (x^2 - y^2)
    y30_z = 0.5 * math.sqrt(7 / math.pi)  # Y_3^0 = 1/4 sqrt(7/pi) (5 z^3 - 3 z)
    y33 = 0.25 * math.sqrt(35 / (2 * math.pi))  # |Y_3^{+-3}| on the x / y axis
    y31 = 0.25 * math.sqrt(21 / (2 * math.pi))  # |Y_3^{+-1}| = 1/4 sqrt(21/2pi) x (5 z^2 - 1) -> x = 1
    expected = torch.zeros(3, 16, dtype=torch.float64)
    expected[:, 0] = y00
    expected[0, 3], expected[1, 1], expected[2, 2] = -y1, -y1, y1
    expected[0, 6] = expected[1, 6] = -0.5 * y20_z
    expected[2, 6] = y20_z
    expected[0, 8], expected[1, 8] = y22_x, -y22_x
    expected[2, 12] = y30_z
    expected[0, 13], expected[0, 15] = y31, -y33  # x (4z^2 - x^2 - y^2) = -1 -> +, x (x^2 - 3y^2) = 1 -> -
    expected[1, 11], expected[1, 9] = y31, y33  # y (3x^2 - y^2) = -1 -> +
    torch.testing.assert_close(basis, expected, rtol=0, atol=1e-12)


def test_sh_basis_orthonormal_on_sphere():
    dirs, weights = sphere_quadrature()
    basis = sh_basis(dirs, 3)
    gram = basis.T @ (basis * weights[:, None])
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), rtol=0, atol=1e-10)


def test_sh_basis_matches_gsplat():
    from gsplat.cuda import _torch_impl as torch_impl  # gsplat is a pinned dependency: no skip without it

    dirs = torch.nn.functional.normalize(
        torch.randn(64, 3, generator=torch.Generator().manual_seed(0)), dim=-1
    )
    torch.testing.assert_close(
        sh_basis(dirs, 3), torch_impl._eval_sh_bases_fast(16, dirs), rtol=1e-5, atol=1e-6
    )


def test_eval_sh_and_visibility():
    dirs = torch.randn(10, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    coeffs = torch.randn(10, 16, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    expected = (coeffs * sh_basis(dirs, 3)).sum(-1)
    torch.testing.assert_close(eval_sh(coeffs, dirs), expected)
    torch.testing.assert_close(eval_sh(coeffs, 5.0 * dirs), expected)  # direction length does not matter
    torch.testing.assert_close(visibility_from_sh(coeffs, dirs), (expected + 0.5).clamp(0, 1))
    zeros = torch.zeros(4, 16)
    assert torch.all(visibility_from_sh(zeros, torch.randn(4, 3)) == 0.5)
    opaque = torch.zeros(4, 16)
    opaque[:, 0] = -0.5 / 0.28209479177387814  # DC cancels the +0.5 offset
    torch.testing.assert_close(visibility_from_sh(opaque, torch.randn(4, 3)), torch.zeros(4))
    # A degree-1 function: f(w) = c1 * (C1 z) is linear in z.
    coeffs1 = torch.tensor([0.0, 0.0, 1.0, 0.0])
    torch.testing.assert_close(eval_sh(coeffs1, torch.tensor([0.0, 0.6, 0.8])), torch.tensor(0.4886025 * 0.8))
    with pytest.raises(ValueError, match="SH coefficient count"):
        eval_sh(torch.zeros(5), torch.tensor([0.0, 0.0, 1.0]))


def test_light_sh_encoding_is_degree2_basis():
    dirs = torch.tensor([[0.0, 0.0, 2.0], [1.0, 1.0, 0.0]])
    enc = light_sh_encoding(dirs)
    assert enc.shape == (2, 9)
    torch.testing.assert_close(enc, sh_basis(dirs, 3)[:, :9])
    torch.testing.assert_close(enc[0], torch.tensor([0.2820948, 0, 0.4886025, 0, 0, 0, 0.6307831, 0, 0]))


# ----------------------------------------------------------------------------- GGX


def reference_ggx(n, v, l, base, r, m, lin, light):
    """Scalar re-derivation of method.md section 3 (plain Python floats) per colour channel."""
    h = np.asarray(l) + np.asarray(v)
    h = h / np.linalg.norm(h)
    nl, nv, nh, vh = float(np.dot(n, l)), float(np.dot(n, v)), float(np.dot(n, h)), float(np.dot(v, h))
    a = r * r
    d = a * a / (math.pi * (nh * nh * (a * a - 1) + 1) ** 2)
    k = (r + 1) ** 2 / 8
    g = (nv / (nv * (1 - k) + k)) * (nl / (nl * (1 - k) + k))
    diffuse, specular = [], []
    for c in range(3):
        f0 = 0.04 + (base[c] - 0.04) * m
        f = f0 + (1 - f0) * 2 ** ((-5.55473 * vh - 6.98316) * vh)
        fs = d * f * g / (4 * nv * nl)
        fd = (1 - f) * (1 - m) * base[c] / math.pi
        diffuse.append(nl * lin * light[c] * fd)
        specular.append(nl * lin * light[c] * fs)
    return np.array(diffuse), np.array(specular)


@pytest.mark.parametrize(
    "config",
    [
        {
            "l_deg": 0.0,
            "v_deg": 0.0,
            "base": (0.5, 0.5, 0.5),
            "r": 0.5,
            "m": 0.0,
            "lin": 1.0,
            "light": (1, 1, 1),
        },
        {
            "l_deg": 60.0,
            "v_deg": -20.0,
            "base": (0.8, 0.4, 0.2),
            "r": 0.7,
            "m": 0.3,
            "lin": 0.6,
            "light": (1, 2, 3),
        },
        {
            "l_deg": 30.0,
            "v_deg": 45.0,
            "base": (0.1, 0.9, 0.5),
            "r": 0.25,
            "m": 0.9,
            "lin": 2.0,
            "light": (1, 1, 1),
        },
    ],
)
def test_pbr_shade_matches_hand_computation(config):
    def unit(deg):
        return (math.sin(math.radians(deg)), 0.0, math.cos(math.radians(deg)))

    n, l, v = (0.0, 0.0, 1.0), unit(config["l_deg"]), unit(config["v_deg"])
    diffuse, specular = reference_ggx(
        n, v, l, config["base"], config["r"], config["m"], config["lin"], config["light"]
    )

    def t(x):
        return torch.tensor(x, dtype=torch.float64)

    terms = pbr_shade(
        t(n),
        t(v),
        t(l),
        t(config["base"]),
        t([config["r"]]),
        t([config["m"]]),
        t([config["lin"]]),
        t(config["light"]),
    )
    torch.testing.assert_close(terms.diffuse, t(diffuse), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(terms.specular, t(specular), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(terms.radiance, t(diffuse + specular))


def test_ggx_terms_known_values():
    r = torch.tensor(0.5, dtype=torch.float64)
    # n.h = 1: D = 1 / (pi a^2), a = r^2.
    one = torch.tensor(1.0, dtype=torch.float64)
    torch.testing.assert_close(ggx_distribution(one, r), one / (math.pi * 0.0625))
    # r = 1: a = 1, D = 1/pi everywhere.
    torch.testing.assert_close(
        ggx_distribution(torch.tensor(0.3), torch.tensor(1.0)), torch.tensor(1 / math.pi)
    )
    k = 1.5**2 / 8
    torch.testing.assert_close(smith_g1(0.5 * one, r), one * 0.5 / (0.5 * (1 - k) + k))
    torch.testing.assert_close(smith_g1(torch.tensor(1.0), torch.tensor(0.3)), torch.tensor(1.0))
    g = geometry_smith(torch.tensor(0.5), torch.tensor(0.25), torch.tensor(0.5))
    torch.testing.assert_close(
        g, smith_g1(torch.tensor(0.5), torch.tensor(0.5)) * smith_g1(torch.tensor(0.25), torch.tensor(0.5))
    )
    # Fresnel: F(v.h = 1) ~ F0, F(v.h = 0) = 1.
    f0 = torch.tensor([0.04, 0.5, 0.9])
    torch.testing.assert_close(fresnel_schlick_ue4(torch.tensor(0.0), f0), torch.ones(3))
    expected = f0 + (1 - f0) * 2 ** (-5.55473 - 6.98316)
    torch.testing.assert_close(fresnel_schlick_ue4(torch.tensor(1.0), f0), expected)


@pytest.mark.parametrize("roughness", [0.2, 0.5, 1.0])
def test_ggx_distribution_is_normalised(roughness):
    mu = torch.linspace(0.0, 1.0, 400_001, dtype=torch.float64)
    integrand = ggx_distribution(mu, torch.tensor(roughness, dtype=torch.float64)) * mu
    integral = 2 * math.pi * torch.trapezoid(integrand, mu)  # int D (n.h) dw_h over the hemisphere
    assert abs(float(integral) - 1.0) < 1e-4


def test_lambertian_part_conserves_energy():
    lights, weights = sphere_quadrature(num_mu=32, num_phi=32, upper_hemisphere=True)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(lights)
    v = torch.tensor([0.6, 0.0, 0.8], dtype=torch.float64).expand_as(lights)
    base = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    one = torch.ones(1, dtype=torch.float64)
    terms = pbr_shade(n, v, lights, base, 0.5 * one, 0 * one, one, torch.ones(3, dtype=torch.float64))
    v_dot_h = (v * torch.nn.functional.normalize(lights + v, dim=-1)).sum(-1, keepdim=True)
    without_fresnel = terms.diffuse / (
        1 - fresnel_schlick_ue4(v_dot_h, torch.full((3,), 0.04, dtype=torch.float64))
    )
    albedo = (without_fresnel * weights[:, None]).sum(0)  # int f_d (n.l) dw_l with F = 0
    torch.testing.assert_close(albedo, base, rtol=1e-6, atol=1e-6)


def test_pbr_shade_zero_below_horizon_and_finite_gradients_at_grazing():
    n = torch.tensor([[0.0, 0.0, 1.0]] * 4, requires_grad=True)
    light = torch.tensor([[1.0, 0.0, -0.1], [1.0, 0.0, 0.0], [1.0, 0.0, 1e-6], [0.0, 1.0, 1e-3]])
    light = torch.nn.functional.normalize(light, dim=-1)
    view = torch.nn.functional.normalize(torch.tensor([[-1.0, 0.0, 1e-6]] * 4), dim=-1)
    base = torch.full((4, 3), 0.5, requires_grad=True)
    rough = torch.full((4, 1), 0.05, requires_grad=True)
    metal = torch.full((4, 1), 0.5, requires_grad=True)
    lin = torch.ones(4, 1, requires_grad=True)
    terms = pbr_shade(n, view, light, base, rough, metal, lin, torch.ones(3))
    assert torch.all(terms.radiance[:2] == 0)
    assert torch.all(torch.isfinite(terms.radiance))
    terms.radiance.sum().backward()
    for tensor in (n, base, rough, metal, lin):
        assert torch.all(torch.isfinite(tensor.grad))


def test_pbr_shade_gradcheck():
    gen = torch.Generator().manual_seed(3)
    n = torch.nn.functional.normalize(
        torch.tensor([[0.1, 0.2, 1.0], [0.0, -0.3, 1.0]], dtype=torch.float64), dim=-1
    )
    v = torch.nn.functional.normalize(
        torch.tensor([[0.3, 0.1, 1.0], [-0.2, 0.0, 1.0]], dtype=torch.float64), dim=-1
    )
    l = torch.nn.functional.normalize(
        torch.tensor([[-0.4, 0.2, 1.0], [0.5, 0.5, 1.0]], dtype=torch.float64), dim=-1
    )
    base = torch.rand(2, 3, generator=gen, dtype=torch.float64).requires_grad_()
    rough = (0.3 + 0.5 * torch.rand(2, 1, generator=gen, dtype=torch.float64)).requires_grad_()
    metal = torch.rand(2, 1, generator=gen, dtype=torch.float64).requires_grad_()
    normal = n.clone().requires_grad_()
    light_dir = l.clone().requires_grad_()

    def shade(normal, light_dir, base, rough, metal):
        return pbr_shade(
            normal, v, light_dir, base, rough, metal, torch.ones(2, 1, dtype=torch.float64), torch.ones(3)
        ).radiance

    assert torch.autograd.gradcheck(shade, (normal, light_dir, base, rough, metal))


# ----------------------------------------------------------------------------- SSS MLP


def test_positional_encoding_known_values():
    x = torch.tensor([[0.25, 0.5, -1.0]], dtype=torch.float64)
    enc = positional_encoding(x, 2)
    expected = [0.25, 0.5, -1.0]
    for k in range(2):
        angles = [2**k * math.pi * value for value in (0.25, 0.5, -1.0)]
        expected += [math.sin(a) for a in angles] + [math.cos(a) for a in angles]
    torch.testing.assert_close(enc, torch.tensor([expected], dtype=torch.float64))
    assert positional_encoding(torch.zeros(5, 7, 3), 4).shape == (5, 7, 27)
    torch.testing.assert_close(positional_encoding(x, 0), x)


def mlp_inputs(batch_shape, num, seed=0):
    gen = torch.Generator().manual_seed(seed)
    shape = (*batch_shape, num)
    return {
        "positions": torch.randn(num, 3, generator=gen),
        "quats": torch.randn(num, 4, generator=gen),
        "scales": torch.rand(num, 3, generator=gen) * 0.1,
        "view_dirs": torch.randn(*shape, 3, generator=gen),
        "light_dirs": torch.randn(*shape, 3, generator=gen),
        "normals": torch.randn(num, 3, generator=gen),
        "visibility": torch.rand(*shape, 1, generator=gen),
        "light_distance": torch.rand(*shape, 1, generator=gen) * 3,
    }


def test_sss_mlp_shapes_ranges_and_batching():
    torch.manual_seed(0)
    mlp = SSSResidualMLP()
    assert mlp.config.width == 32 and mlp.input_dim == 45
    single = mlp(**mlp_inputs((), 50))
    assert single.residual.shape == (50, 3) and single.incident.shape == (50, 1)
    inputs = mlp_inputs((4,), 50)
    batched = mlp(**inputs)
    assert batched.residual.shape == (4, 50, 3) and batched.incident.shape == (4, 50, 1)
    assert torch.all((batched.residual > 0) & (batched.residual < 1))
    assert torch.all(batched.incident >= 0)
    per_light = {k: (v[2] if v.dim() == 3 else v) for k, v in inputs.items()}
    torch.testing.assert_close(mlp(**per_light).residual, batched.residual[2])
    # Quaternions and directions are normalised inside.
    scaled = dict(inputs, quats=3.0 * inputs["quats"], view_dirs=2.0 * inputs["view_dirs"])
    torch.testing.assert_close(mlp(**scaled).incident, batched.incident)
    with pytest.raises(ValueError, match="quats"):
        mlp(**dict(inputs, quats=torch.zeros(50, 3)))


def test_sss_mlp_angular_inputs_are_the_three_cosines():
    torch.manual_seed(0)
    mlp = SSSResidualMLP(SSSMLPConfig(angular_inputs=True))
    assert mlp.input_dim == 48
    inputs = mlp_inputs((3,), 40)
    angular = slice(45, 48)
    with torch.no_grad():  # only the cosines reach the trunk
        first = mlp.trunk[0].weight
        first[:, : angular.start] = 0.0
    rotation = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(1)))[0]
    rotated = dict(inputs, **{k: inputs[k] @ rotation.T for k in ("view_dirs", "light_dirs", "normals")})
    moved = dict(rotated, positions=inputs["positions"] + 0.3, light_distance=inputs["light_distance"] * 2.0)
    # a rigid rotation of normal, view and light (and any other input) leaves n.l, n.v, v.l and the output alone
    torch.testing.assert_close(mlp(**moved).residual, mlp(**inputs).residual)
    swapped = dict(inputs, light_dirs=inputs["view_dirs"], view_dirs=inputs["light_dirs"])
    assert not torch.allclose(mlp(**swapped).residual, mlp(**inputs).residual)  # n.l and n.v are told apart
    seen = []
    mlp.trunk[0].register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    mlp(**inputs)
    n, v, l = (torch.nn.functional.normalize(inputs[k], dim=-1) for k in ("normals", "view_dirs", "light_dirs"))
    cosines = torch.stack([(n * l).sum(-1), (n * v).sum(-1), (v * l).sum(-1)], -1)
    torch.testing.assert_close(seen[0][..., angular], cosines)


def test_sss_mlp_deterministic_init_and_gradients():
    torch.manual_seed(7)
    a = SSSResidualMLP(SSSMLPConfig(width=16))
    torch.manual_seed(7)
    b = SSSResidualMLP(SSSMLPConfig(width=16))
    for pa, pb in zip(a.parameters(), b.parameters()):
        assert torch.equal(pa, pb)
    inputs = mlp_inputs((2,), 20)
    inputs["positions"].requires_grad_()
    out = a(**inputs)
    assert out.incident.mean() > 0.5  # incident head starts near 1 (active ReLU)
    (out.residual.sum() + out.incident.sum()).backward()
    assert inputs["positions"].grad is not None and inputs["positions"].grad.abs().sum() > 0
    for name, param in a.named_parameters():
        assert param.grad is not None and torch.isfinite(param.grad).all(), name
        assert param.grad.abs().sum() > 0, name


def test_light_geometry_feeds_the_mlp():
    means = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    geometry = light_geometry(means, torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 3.0, 0.0]]))
    torch.testing.assert_close(geometry.light_distance, torch.tensor([[[math.sqrt(10.0)], [3.0]]]))
    torch.testing.assert_close(geometry.light_dirs[0, 1], torch.tensor([0.0, 1.0, 0.0]))
    torch.testing.assert_close(geometry.view_dirs[0, 1], torch.tensor([-1.0, 0.0, 2.0]) / math.sqrt(5.0))
    torch.manual_seed(0)
    out = SSSResidualMLP()(
        means,
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(2, 4),
        torch.full((2, 3), 0.1),
        geometry.view_dirs,
        geometry.light_dirs,
        torch.tensor([[0.0, 0.0, 1.0]]).expand(2, 3),
        torch.ones(1, 2, 1),
        geometry.light_distance,
    )
    assert out.residual.shape == (1, 2, 3)
    with pytest.raises(ValueError, match="camera_center and light_pos"):
        light_geometry(means, torch.zeros(2, 3), torch.zeros(1, 3))


# ----------------------------------------------------------------------------- deferred shading


def plane_scene(size=5, light_height=2.0, s=0.3, alpha=1.0):
    """Camera at (0, 0, 2) looking down at the plane z = 0 (normal +z), light at (0, 0, light_height)."""
    eye = torch.tensor([0.0, 0.0, 2.0])
    w2c = opengl_c2w_to_opencv_w2c(look_at_opengl_c2w(eye, torch.zeros(3))).float()[None]
    K = torch.tensor([[[4.0, 0.0, size / 2], [0.0, 4.0, size / 2], [0.0, 0.0, 1.0]]])

    def full(channels, value):
        return torch.full((1, size, size, channels), float(value))

    gbuffer = GBuffer(
        normal=full(3, 0.0) + torch.tensor([0.0, 0.0, 3.0]),  # unnormalised blend
        base_color=full(3, 0.0) + torch.tensor([0.8, 0.5, 0.2]),
        roughness=full(1, 0.6),
        metallic=full(1, 0.1),
        subsurface=full(1, s),
        visibility=full(1, 0.9),
        incident=full(1, 0.7),
        residual=full(3, 0.0) + torch.tensor([0.3, 0.2, 0.1]),
        depth=full(1, 2.0),
        alpha=full(1, alpha),
    )
    light_pos = torch.tensor([[0.0, 0.0, light_height]])
    light_rgb = torch.tensor([[1.0, 0.9, 0.8]])
    return gbuffer, w2c, K, light_pos, light_rgb


def test_deferred_flat_plane_matches_hand_computation():
    gbuffer, w2c, K, light_pos, light_rgb = plane_scene(size=5, light_height=2.0)
    scale = torch.tensor(math.exp(-1.0))
    result = deferred_shade(gbuffer, w2c, K, light_pos, light_rgb, scale)
    intensity = (scale * light_rgb[0]).tolist()
    base, s, lin, residual = (0.8, 0.5, 0.2), 0.3, 0.7, np.array([0.3, 0.2, 0.1])
    for i in range(5):
        for j in range(5):
            # Pixel (i, j) sees x = (z (u - cx) / fx, -z (v - cy) / fy, 0): OpenCV +y (down) is world -y.
            x = np.array([2.0 * (j + 0.5 - 2.5) / 4.0, -2.0 * (i + 0.5 - 2.5) / 4.0, 0.0])
            to_light = np.array([0.0, 0.0, 2.0]) - x
            l = to_light / np.linalg.norm(to_light)
            v = l  # light and camera coincide
            diffuse, specular = reference_ggx((0, 0, 1), v, l, base, 0.6, 0.1, lin, intensity)
            expected = (1 - s) * (diffuse + specular) + s * residual * np.array(intensity)
            torch.testing.assert_close(
                result.radiance[0, i, j].double(), torch.from_numpy(expected), rtol=1e-5, atol=1e-6
            )
            torch.testing.assert_close(
                result.points[0, i, j].double(), torch.from_numpy(x), rtol=0, atol=1e-5
            )
    # Centre pixel: n = l = v, D = 1 / (pi a^2), G = 1, f_s = D F / 4.
    a = 0.6**2
    f = [0.04 + (b - 0.04) * 0.1 + (1 - (0.04 + (b - 0.04) * 0.1)) * 2 ** (-5.55473 - 6.98316) for b in base]
    centre = [
        (1 - s) * lin * intensity[c] * ((1 - f[c]) * 0.9 * base[c] / math.pi + f[c] / (4 * math.pi * a * a))
        + s * residual[c] * intensity[c]
        for c in range(3)
    ]
    torch.testing.assert_close(
        result.radiance[0, 2, 2], torch.tensor(centre, dtype=torch.float32), rtol=1e-5, atol=1e-6
    )


def test_deferred_inverse_square_falloff_relative_to_the_centre():
    gbuffer, w2c, K, light_pos, light_rgb = plane_scene(size=5, light_height=2.0)
    scale = torch.tensor(0.5)
    plain = deferred_shade(gbuffer, w2c, K, light_pos, light_rgb, scale)
    center = torch.tensor([0.0, 0.0, -1.0])
    fallen = deferred_shade(gbuffer, w2c, K, light_pos, light_rgb, scale, falloff_center=center)
    for i, j in ((2, 2), (0, 0), (1, 4)):
        x = np.array([2.0 * (j + 0.5 - 2.5) / 4.0, -2.0 * (i + 0.5 - 2.5) / 4.0, 0.0])
        factor = 3.0**2 / np.sum((np.array([0.0, 0.0, 2.0]) - x) ** 2)  # |p - c|^2 / |p - x|^2
        torch.testing.assert_close(fallen.radiance[0, i, j], plain.radiance[0, i, j] * float(factor))
        torch.testing.assert_close(fallen.residual[0, i, j], plain.residual[0, i, j] * float(factor))
    # a surface point at the centre's distance from the light is lit as without falloff
    same = deferred_shade(gbuffer, w2c, K, light_pos, light_rgb, scale, falloff_center=torch.zeros(3))
    torch.testing.assert_close(same.radiance[0, 2, 2], plain.radiance[0, 2, 2])
    light = light_pos.double().requires_grad_()

    def shade(position):
        double = GBuffer(**{name: getattr(gbuffer, name).double() for name in
                            ("normal", "base_color", "roughness", "metallic", "subsurface", "visibility", "incident",
                             "residual", "depth", "alpha")})
        return deferred_shade(double, w2c.double(), K.double(), position, light_rgb.double(), scale.double(),
                              falloff_center=center.double()).radiance

    assert torch.autograd.gradcheck(shade, (light,))


def test_scene_light_falloff_is_a_checked_config_key():
    assert make_config("diamond").shading.light_falloff == "none"  # as SSS-3DGS
    assert CHOICES["shading.light_falloff"] == LIGHT_FALLOFFS
    with pytest.raises(ValueError, match="shading.light_falloff"):
        make_config("diamond", overrides={"light_falloff": "linear"})


def test_deferred_alpha_premultiplies_and_decomposes():
    gbuffer, w2c, K, light_pos, light_rgb = plane_scene(size=4, light_height=3.0)
    scale = torch.tensor(0.5)
    opaque = deferred_shade(gbuffer, w2c, K, light_pos, light_rgb, scale)
    alpha = torch.rand(1, 4, 4, 1, generator=torch.Generator().manual_seed(0))
    alpha[0, 0, :2] = 0.0
    gbuffer.alpha = alpha
    gbuffer.normal = gbuffer.normal.clone()
    gbuffer.normal[0, 0, :2] = 0.0  # uncovered pixels hold zeros / garbage
    gbuffer.depth = gbuffer.depth.clone()
    gbuffer.depth[0, 0, :2] = 0.0
    blended = deferred_shade(gbuffer, w2c, K, light_pos, light_rgb, scale)
    assert torch.all(blended.radiance[0, 0, :2] == 0)
    torch.testing.assert_close(blended.radiance[0, 1:], opaque.radiance[0, 1:] * alpha[0, 1:])
    s = gbuffer.subsurface
    torch.testing.assert_close(blended.radiance, (1 - s) * blended.pbr + s * blended.residual)
    torch.testing.assert_close(blended.pbr, blended.diffuse + blended.specular)


def test_deferred_light_below_surface_leaves_only_residual_and_gradients_flow():
    gbuffer, w2c, K, _, light_rgb = plane_scene(size=3)
    light_pos = torch.tensor([[0.0, 0.0, -2.0]])
    scale = torch.tensor(0.4, requires_grad=True)
    gbuffer.residual.requires_grad_()
    result = deferred_shade(gbuffer, w2c, K, light_pos, light_rgb, scale)
    assert torch.all(result.pbr == 0)
    torch.testing.assert_close(result.radiance, 0.3 * result.residual)
    torch.testing.assert_close(result.residual[0, 1, 1], torch.tensor([0.3, 0.2, 0.1]) * light_rgb[0] * 0.4)
    result.radiance.sum().backward()
    torch.testing.assert_close(scale.grad, result.radiance.sum().detach() / 0.4)
    assert gbuffer.residual.grad.abs().sum() > 0


def test_gbuffer_from_features_round_trip_and_validation():
    gbuffer, *_ = plane_scene(size=3)
    names = [name for name, _ in GBUFFER_FEATURES]
    stacked = torch.cat([getattr(gbuffer, name) for name in names], dim=-1)
    assert stacked.shape[-1] == GBUFFER_FEATURE_DIM
    alpha = torch.full((1, 3, 3, 1), 0.5)
    alpha[0, 0, 0] = 0.0
    rebuilt = GBuffer.from_features(stacked * alpha, gbuffer.depth, alpha)
    for name in names:
        torch.testing.assert_close(getattr(rebuilt, name)[0, 1:], getattr(gbuffer, name)[0, 1:])
        assert torch.all(getattr(rebuilt, name)[0, 0, 0] == 0)
    assert torch.equal(rebuilt.depth, gbuffer.depth)
    with pytest.raises(ValueError, match="GBuffer.roughness"):
        GBuffer(**dict(vars(gbuffer), roughness=torch.zeros(1, 3, 3, 2)))
    with pytest.raises(ValueError, match="light_pos"):
        deferred_shade(
            gbuffer,
            torch.eye(4)[None],
            torch.eye(3)[None],
            torch.zeros(3),
            torch.ones(1, 3),
            torch.tensor(1.0),
        )


def test_deferred_gradients_finite_with_uncovered_pixels():
    gbuffer, w2c, K, light_pos, light_rgb = plane_scene(size=4)
    for name in ("depth", "normal", "alpha"):
        value = getattr(gbuffer, name).clone()
        value[0, 0] = 0.0  # an uncovered row: zero depth, zero normal, zero alpha
        setattr(gbuffer, name, value.requires_grad_())
    w2c.requires_grad_()
    result = deferred_shade(gbuffer, w2c, K, light_pos, light_rgb, torch.tensor(0.5))
    result.radiance.sum().backward()
    for grad in (gbuffer.depth.grad, gbuffer.normal.grad, gbuffer.alpha.grad, w2c.grad):
        assert torch.isfinite(grad).all()
    assert gbuffer.depth.grad[0, 1:].abs().sum() > 0
