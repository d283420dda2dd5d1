"""The depth below the lit surface (``shading/light_depth.py``) and its use as an MLP input."""

from __future__ import annotations

import copy
import math

import pytest
import torch
import torch.nn.functional as F

from diamond_sss.data.conventions import camera_centers, project_points
from diamond_sss.gaussians.model import GaussianModel
from diamond_sss.scene.model import RelightableScene
from diamond_sss.shading.light_depth import (
    COVERAGE_MARGIN,
    MAX_HALF_ANGLE,
    CachedLights,
    LightMapCache,
    depth_below_surface,
    light_cameras,
)
from diamond_sss.shading.sss_mlp import SSSMLPConfig, SSSResidualMLP
from diamond_sss.training.overrides import make_config


def test_light_cameras_sit_at_the_lights_and_frame_the_bounding_sphere():
    lights = torch.tensor([[0.0, 0.0, 5.0], [3.0, -4.0, 1.0], [0.2, 0.1, -2.5]])
    center, radius, size = torch.tensor([0.1, -0.2, 0.3]), 0.8, 32
    w2c, K = light_cameras(lights, center, radius, size)
    torch.testing.assert_close(camera_centers(w2c), lights, atol=1e-5, rtol=0)
    uv, z = project_points(center.expand(3, 1, 3), w2c, K)
    torch.testing.assert_close(uv[:, 0], torch.full((3, 2), size / 2))  # looks at the centre
    torch.testing.assert_close(z[:, 0], (lights - center).norm(dim=-1))
    for b in range(3):  # the grown sphere's silhouette touches the image border: tangent rays at the edge
        distance = float((lights[b] - center).norm())
        half_angle = math.asin(COVERAGE_MARGIN * radius / distance)
        assert K[b, 0, 0].item() == pytest.approx(0.5 * size / math.tan(half_angle), rel=1e-5)
    _, K_inside = light_cameras(torch.tensor([[0.1, -0.2, 0.8]]), center, radius, size)  # a light inside the sphere
    assert K_inside[0, 0, 0].item() == pytest.approx(0.5 * size / math.tan(MAX_HALF_ANGLE), rel=1e-5)


def test_depth_below_surface_known_answers():
    w2c, K = light_cameras(torch.tensor([[0.0, 0.0, 4.0]]), torch.zeros(3), 1.0, 8)
    depth = torch.full((1, 8, 8, 1), 3.5)
    alpha = torch.ones(1, 8, 8, 1)
    alpha[:, :, :2] = 0.0  # the left two columns saw no surface
    on_axis = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.7], [0.0, 0.0, -0.25]])  # light depths 4, 3.3, 4.25
    left = torch.tensor([[-0.9, 0.0, -0.5]])  # projects into the uncovered columns
    behind = torch.tensor([[0.0, 0.0, 4.5]])  # behind the light camera
    points = torch.cat([on_axis, left, behind])
    t = depth_below_surface(points, w2c, K, depth, alpha)
    assert t.shape == (1, 5, 1)
    torch.testing.assert_close(t[0, :, 0], torch.tensor([0.5, 0.0, 0.75, 0.0, 0.0]))


def sphere_of_gaussians(count: int = 1500, radius: float = 1.0) -> GaussianModel:
    golden = math.pi * (3.0 - math.sqrt(5.0))
    k = torch.arange(count, dtype=torch.float32)
    z = 1.0 - 2.0 * (k + 0.5) / count
    ring = (1.0 - z * z).sqrt()
    points = radius * torch.stack([ring * torch.cos(golden * k), ring * torch.sin(golden * k), z], -1)
    model = GaussianModel.from_points(points, None, points, init_scale=0.06, init_opacity=0.95)
    return model


def test_scene_light_depth_of_an_opaque_sphere_is_its_chord_along_the_light():
    radius = 1.0
    model = sphere_of_gaussians(radius=radius)
    scene = RelightableScene(model, sss_width=16, scene_center=torch.zeros(3), scene_radius=radius,
                             sss_light_depth=48)
    assert scene.mlp.input_dim == 45 + 1
    light = torch.tensor([[0.0, 0.0, 5.0]])
    t = scene.light_depth(light)[0, :, 0]
    means = model.means.detach()
    facing = means @ F.normalize(light[0], dim=0)  # height towards the light
    # a point at height h on the unit sphere lies the chord 2h below the top cap on its (near-vertical) light ray
    back = facing < -0.5
    expected = -2.0 * means[back, 2]
    front = t[facing > 0.5]  # on the lit cap: zero up to the Gaussians' footprint (scale 0.06)
    assert front.median() < 0.07 and front.max() < 0.2
    torch.testing.assert_close(t[back], expected, atol=0.2, rtol=0.1)
    lit = scene.render(torch.eye(4).expand(1, 4, 4).clone(), torch.eye(3)[None], 4, 4, light, torch.ones(1, 3))
    assert torch.isfinite(lit.radiance).all()


def test_light_depth_is_a_checked_config_key_off_by_default():
    assert make_config("diamond").shading.sss_light_depth == 0
    assert make_config("diamond", overrides={"sss_light_depth": 32}).shading.sss_light_depth == 32
    with pytest.raises(ValueError, match="sss_light_depth"):
        RelightableScene(sphere_of_gaussians(count=10), sss_light_depth=-1)
    for key in ("sss_light_depth", "sss_lr_warmup_steps"):  # refused when configured, naming the key
        with pytest.raises(ValueError, match=f"config key '.*{key.removeprefix('sss_lr_')}' must be >= 0, got -1"):
            make_config("diamond", sets=[f"{key}=-1"])


def test_sss_mlp_light_depth_input_is_its_last_column():
    gen = torch.Generator().manual_seed(0)
    mlp = SSSResidualMLP(SSSMLPConfig(width=16, light_depth_input=True))
    inputs = {name: torch.randn(*lead, 30, channels, generator=gen) for name, lead, channels in (
        ("positions", (), 3), ("quats", (), 4), ("scales", (), 3), ("view_dirs", (2,), 3), ("light_dirs", (2,), 3),
        ("normals", (), 3), ("visibility", (2,), 1), ("light_distance", (2,), 1))}
    with pytest.raises(ValueError, match="light_depth"):
        mlp(**inputs)
    depth = torch.rand(2, 30, 1)
    seen = []
    mlp.trunk[0].register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    out = mlp(**inputs, light_depth=depth)
    assert seen[0].shape[-1] == mlp.input_dim == 46
    torch.testing.assert_close(seen[0][..., -1:], depth)
    assert not torch.allclose(mlp(**inputs, light_depth=depth + 1.0).residual, out.residual)
    with pytest.raises(ValueError, match="light_depth"):
        mlp(**inputs, light_depth=depth[..., :0])


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_light_depth_cpu_cuda_parity():
    scene = RelightableScene(sphere_of_gaussians(), scene_center=torch.zeros(3), scene_radius=1.0, sss_light_depth=48)
    lights = torch.tensor([[0.0, 0.0, 5.0], [3.0, -4.0, 1.0]])
    cpu = scene.light_depth(lights)
    gpu = scene.to("cuda").light_depth(lights.cuda())
    assert gpu.device.type == "cuda"
    # the rasterizers differ in float32 rounding: compare where the depth map is smooth (all but a few edge texels)
    assert ((cpu - gpu.cpu()).abs() < 1e-2).float().mean() > 0.99


def test_depth_below_surface_of_no_points_and_of_an_empty_map():
    w2c, K = light_cameras(torch.tensor([[0.0, 0.0, 4.0]]), torch.zeros(3), 1.0, 8)
    depth, alpha = torch.full((1, 8, 8, 1), 3.5), torch.ones(1, 8, 8, 1)
    assert depth_below_surface(torch.zeros(0, 3), w2c, K, depth, alpha).shape == (1, 0, 1)
    t = depth_below_surface(torch.zeros(5, 3), w2c, K, depth, torch.zeros_like(alpha))  # the light sees nothing
    assert torch.equal(t, torch.zeros(1, 5, 1))


def test_light_map_cache_renders_each_light_once_per_window_in_the_batch_order():
    cache = LightMapCache(every=4)
    calls = []

    def render(rows):  # the map of batch row r is filled with 10 r + the call's number
        calls.append(rows)
        maps = torch.stack([torch.full((2, 2, 1), 10.0 * row + len(calls)) for row in rows])
        return maps, -maps

    cache.start_step(0)
    depth, alpha = cache.maps(["a", "b", "a"], render)
    assert calls == [[0, 1]] and len(cache) == 2
    torch.testing.assert_close(depth[:, 0, 0, 0], torch.tensor([1.0, 11.0, 1.0]))
    torch.testing.assert_close(alpha, -depth)
    cache.start_step(3)  # same window: only the new light is rendered, the others come back as they were
    depth, _ = cache.maps(["c", "b"], render)
    assert calls[-1] == [0] and depth[:, 0, 0, 0].tolist() == [2.0, 11.0]
    cache.start_step(4)  # a new window: everything again
    depth, _ = cache.maps(["b"], render)
    assert calls[-1] == [0] and depth[0, 0, 0, 0].item() == 3.0 and len(cache) == 1
    cache.clear()
    assert len(cache) == 0
    with pytest.raises(ValueError, match="every=0"):
        LightMapCache(0)


def test_scene_light_depth_from_the_cache_equals_a_fresh_render_then_lags_the_geometry():
    scene = RelightableScene(sphere_of_gaussians(), scene_center=torch.zeros(3), scene_radius=1.0, sss_light_depth=32)
    lights = torch.tensor([[0.0, 0.0, 5.0], [3.0, -4.0, 1.0], [0.0, 0.0, 5.0]])
    cached = CachedLights(LightMapCache(every=10), keys=[0, 1, 0])
    fresh = scene.light_depth(lights)
    assert torch.equal(scene.light_depth(lights, cached), fresh)
    before = copy.deepcopy(scene)
    with torch.no_grad():  # the geometry moves: the cached maps are those of the first use, the points are new
        scene.gaussians.params["means"].mul_(0.9)
    moved, reused = scene.light_depth(lights), scene.light_depth(lights, cached)
    assert not torch.equal(moved, reused)
    w2c, K = light_cameras(lights, scene.scene_center, scene.scene_radius, 32)
    old_maps = before.render_geometry(w2c, K, 32, 32)
    expected = depth_below_surface(scene.gaussians.means, w2c, K, old_maps.depth, old_maps.alpha)
    assert torch.equal(reused, expected)
