from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement
from safetensors.torch import load_file, save_file

from diamond_sss.data.conventions import (
    camera_centers,
    intrinsics_from_fov,
    look_at_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    pixel_ray_directions,
    project_points,
    srgb_to_linear,
)
from diamond_sss.gaussians import (
    NUM_VISIBILITY_SH,
    PARAM_SHAPES,
    SH_C0,
    EmptyVisualHullError,
    GaussianModel,
    carve_visual_hull,
    export_ply,
    import_ply,
    initial_points,
    load_points3d_ply,
    nearest_neighbor_scales,
    random_points_in_sphere,
    visual_hull_points,
)

SPHERE_CENTER = torch.tensor([0.1, -0.2, 0.15])
SPHERE_RADIUS = 0.5
BOUNDS_CENTER = SPHERE_CENTER + torch.tensor([0.2, -0.1, 0.05])  # off the sphere: breaks grid symmetry
BOUNDS_RADIUS = 1.0
LOOK_AT = SPHERE_CENTER + torch.tensor([0.12, -0.08, 0.05])
AXES = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]


def _random_model(num: int = 50, seed: int = 0) -> GaussianModel:
    generator = torch.Generator().manual_seed(seed)
    raw = {name: torch.randn(num, *shape, generator=generator) for name, shape in PARAM_SHAPES.items()}
    return GaussianModel(raw)


def _sphere_rig(directions, distance: float = 2.0, size: int = 48, fov_factor: float = 1.6):
    """Cameras at ``distance`` from the sphere centre looking at ``LOOK_AT`` (off-centre, so that the
    silhouettes are off-centre ellipses), with exact silhouettes as masks.

    A pixel is foreground when its ray passes within ``SPHERE_RADIUS`` of the centre: the angle between
    the ray and the direction to the centre is at most ``asin(r / d)``. The field of view frames the
    whole bounding sphere unless ``fov_factor`` is small.
    """
    fov = 2.0 * math.asin(fov_factor * BOUNDS_RADIUS / distance)
    K = intrinsics_from_fov(fov, size, size)
    masks, w2cs = [], []
    for direction in directions:
        direction = torch.tensor(direction, dtype=torch.float64)
        eye = SPHERE_CENTER.double() + distance * direction / direction.norm()
        w2c = opengl_c2w_to_opencv_w2c(look_at_opengl_c2w(eye, LOOK_AT.double())).float()
        rays = pixel_ray_directions(w2c, K, size, size)
        to_center = SPHERE_CENTER - camera_centers(w2c)
        cos_limit = math.sqrt(1.0 - (SPHERE_RADIUS / float(to_center.norm())) ** 2)
        masks.append((rays @ (to_center / to_center.norm()) >= cos_limit).float())
        w2cs.append(w2c)
    return torch.stack(masks), torch.stack(w2cs), K.expand(len(directions), 3, 3).clone()


def _fibonacci_directions(n: int) -> torch.Tensor:
    index = torch.arange(n, dtype=torch.float32) + 0.5
    z = 1.0 - 2.0 * index / n
    phi = math.pi * (1.0 + 5.0**0.5) * index
    rho = (1.0 - z**2).sqrt()
    return torch.stack([rho * phi.cos(), rho * phi.sin(), z], dim=-1)


# ----------------------------------------------------------------------------------------------- model


def test_from_points_activations_and_defaults():
    generator = torch.Generator().manual_seed(0)
    points = torch.randn(40, 3, generator=generator)
    colors = torch.rand(40, 3, generator=generator) * 0.9 + 0.05
    model = GaussianModel.from_points(
        points, colors, init_scale=0.02, init_opacity=0.1, init_roughness=0.3, generator=generator
    )
    assert model.num_gaussians == 40
    assert set(model.params.keys()) == set(PARAM_SHAPES)
    for name, shape in PARAM_SHAPES.items():
        assert model.params[name].shape == (40, *shape)
    torch.testing.assert_close(model.means, points)
    torch.testing.assert_close(model.scales, torch.full((40, 3), 0.02))
    torch.testing.assert_close(model.params["scales"], torch.full((40, 3), math.log(0.02)))
    torch.testing.assert_close(model.opacities, torch.full((40,), 0.1))
    torch.testing.assert_close(model.base_color, colors)
    torch.testing.assert_close(model.roughness, torch.full((40, 1), 0.3))
    torch.testing.assert_close(model.quats.norm(dim=-1), torch.ones(40))
    torch.testing.assert_close(model.normals.norm(dim=-1), torch.ones(40))
    for name in ("metallic", "subsurface"):
        value = getattr(model, name)
        assert value.shape == (40, 1) and bool(((value > 0) & (value < 1)).all())
    # Visibility: SH value C0 * dc = 0.5 so that v = clamp(SH + 0.5, 0, 1) = 1; higher bands are zero.
    assert model.visibility_sh.shape == (40, NUM_VISIBILITY_SH)
    torch.testing.assert_close(SH_C0 * model.visibility_sh[:, 0], torch.full((40,), 0.5))
    assert bool((model.visibility_sh[:, 1:] == 0).all())


def test_activations_follow_raw_parameters():
    model = _random_model()
    raw = model.params
    torch.testing.assert_close(model.scales, raw["scales"].exp())
    torch.testing.assert_close(model.opacities, torch.sigmoid(raw["opacities"]))
    torch.testing.assert_close(model.quats, raw["quats"] / raw["quats"].norm(dim=-1, keepdim=True))
    torch.testing.assert_close(model.normals, raw["normals"] / raw["normals"].norm(dim=-1, keepdim=True))
    for name in ("base_color", "roughness", "metallic", "subsurface"):
        torch.testing.assert_close(getattr(model, name), torch.sigmoid(raw[name]))
    assert model.visibility_sh is raw["visibility_sh"]


def test_default_normals_point_away_from_centroid_and_colour_defaults():
    points = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 2, 0], [0, -2, 0], [0, 0, 3], [0, 0, -3]]) + 5.0
    model = GaussianModel.from_points(points, init_scale=0.1)
    expected = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    torch.testing.assert_close(model.normals, expected)
    torch.testing.assert_close(model.base_color, torch.full((6, 3), 0.5))
    given = GaussianModel.from_points(
        points, normals=torch.tensor([[0.0, 0.0, 2.0]]).expand(6, 3), init_scale=0.1
    )
    torch.testing.assert_close(given.normals, torch.tensor([[0.0, 0.0, 1.0]]).expand(6, 3))


def test_nearest_neighbor_scales_on_a_grid():
    spacing = 0.07
    axis = torch.arange(5, dtype=torch.float32) * spacing
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    scales = nearest_neighbor_scales(grid)
    # Every grid point has at least 3 neighbours at exactly one spacing.
    torch.testing.assert_close(scales, torch.full((125,), spacing))
    # Against brute force on a random cloud: RMS of the 3 smallest non-self distances.
    points = torch.randn(60, 3, generator=torch.Generator().manual_seed(1))
    dists = torch.cdist(points, points) + torch.eye(60) * 1e9
    expected = dists.topk(3, largest=False).values.square().mean(dim=1).sqrt()
    torch.testing.assert_close(nearest_neighbor_scales(points), expected)
    model = GaussianModel.from_points(points)
    torch.testing.assert_close(model.scales, expected[:, None].expand(60, 3))


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match=r"\[N,3\]"):
        GaussianModel.from_points(torch.zeros(5, 2))
    with pytest.raises(ValueError, match="init_opacity"):
        GaussianModel.from_points(torch.randn(5, 3), init_opacity=1.0, init_scale=0.1)
    with pytest.raises(ValueError, match="at least 4 points"):
        GaussianModel.from_points(torch.randn(2, 3))
    raw = _random_model(3).state_tensors()
    raw["roughness"] = torch.zeros(3)
    with pytest.raises(ValueError, match="'roughness' must have shape"):
        GaussianModel.from_state_tensors(raw)
    del raw["roughness"]
    with pytest.raises(ValueError, match="missing keys"):
        GaussianModel.from_state_tensors(raw)


def test_from_points_is_deterministic_under_a_seed():
    points = torch.randn(30, 3, generator=torch.Generator().manual_seed(3))

    def build(seed: int) -> GaussianModel:
        return GaussianModel.from_points(points, generator=torch.Generator().manual_seed(seed))

    torch.testing.assert_close(build(7).params["quats"], build(7).params["quats"], rtol=0, atol=0)
    assert not torch.equal(build(7).params["quats"], build(8).params["quats"])


def test_state_tensors_safetensors_round_trip(tmp_path):
    model = _random_model(20)
    state = model.state_tensors()
    for tensor in state.values():
        assert tensor.device.type == "cpu" and tensor.is_contiguous() and not tensor.requires_grad
    save_file(state, str(tmp_path / "gaussians.safetensors"))
    loaded = GaussianModel.from_state_tensors(load_file(str(tmp_path / "gaussians.safetensors")))
    for name in PARAM_SHAPES:
        assert torch.equal(loaded.params[name], model.params[name])
    state["means"].add_(1.0)
    assert not torch.equal(state["means"], model.params["means"])


def test_gsplat_strategy_ops_keep_parameters_and_optimizer_states_aligned():
    from gsplat.strategy import DefaultStrategy
    from gsplat.strategy.ops import duplicate, remove, reset_opa, split

    num = 12
    model = _random_model(num)
    optimizers = {name: torch.optim.Adam([param], lr=1e-3) for name, param in model.params.items()}
    DefaultStrategy().check_sanity(model.params, optimizers)
    loss = sum(param.square().sum() for param in model.params.values())
    loss.backward()
    for optimizer in optimizers.values():
        optimizer.step()
    state = {"grad2d": torch.arange(num, dtype=torch.float32)}

    def check(expected: int) -> None:
        assert model.num_gaussians == expected and state["grad2d"].shape == (expected,)
        for name, param in model.params.items():
            assert param.shape == (expected, *PARAM_SHAPES[name]) and param.requires_grad
            optimizer = optimizers[name]
            assert optimizer.param_groups[0]["params"][0] is param
            for key in ("exp_avg", "exp_avg_sq"):
                assert optimizer.state[param][key].shape == param.shape

    before = {name: param.detach().clone() for name, param in model.params.items()}
    exp_avg_before = optimizers["base_color"].state[model.params["base_color"]]["exp_avg"].clone()
    mask = torch.zeros(num, dtype=torch.bool)
    mask[[1, 4]] = True
    duplicate(model.params, optimizers, state, mask)
    check(num + 2)
    for name in PARAM_SHAPES:
        assert torch.equal(model.params[name][num:], before[name][[1, 4]])
    exp_avg = optimizers["base_color"].state[model.params["base_color"]]["exp_avg"]
    assert torch.equal(exp_avg[:num], exp_avg_before) and bool((exp_avg[num:] == 0).all())

    split_mask = torch.zeros(num + 2, dtype=torch.bool)
    split_mask[0] = True
    torch.manual_seed(0)
    split(model.params, optimizers, state, split_mask)
    check(num + 3)
    torch.testing.assert_close(model.scales[-1], before["scales"][0].exp() / 1.6)
    assert torch.equal(model.params["visibility_sh"][-1], before["visibility_sh"][0])

    remove_mask = torch.zeros(num + 3, dtype=torch.bool)
    remove_mask[:5] = True
    remove(model.params, optimizers, state, remove_mask)
    check(num - 2)

    reset_opa(model.params, optimizers, state, value=0.01)
    check(num - 2)
    assert bool((model.opacities <= 0.01 + 1e-6).all())
    DefaultStrategy().check_sanity(model.params, optimizers)
    # The model still trains after the surgery.
    model.base_color.sum().backward()
    optimizers["base_color"].step()


# ------------------------------------------------------------------------------------- initialisation


def _assert_contains_sphere(hull) -> None:
    """Every voxel whose centre lies well inside the sphere survives the carving."""
    index = torch.stack(torch.meshgrid(*(torch.arange(hull.occupied.shape[0]),) * 3, indexing="ij"), -1)
    centers = hull.centers(index.reshape(-1, 3))
    well_inside = (centers - SPHERE_CENTER).norm(dim=-1) < SPHERE_RADIUS - hull.voxel_size
    assert int(well_inside.sum()) > 0
    assert bool(hull.occupied.reshape(-1)[well_inside].all())


def test_visual_hull_of_a_sphere_from_six_views():
    masks, w2c, K = _sphere_rig(AXES)
    resolution = 40
    hull = carve_visual_hull(masks, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=resolution)
    _assert_contains_sphere(hull)
    voxel = hull.voxel_size
    num_surface = int(hull.surface().sum())
    points = visual_hull_points(
        masks,
        w2c,
        K,
        SPHERE_CENTER,
        BOUNDS_RADIUS,
        resolution=resolution,
        num_points=2 * num_surface,
        generator=torch.Generator().manual_seed(0),
    )
    assert points.shape == (2 * num_surface, 3)
    radii = (points - SPHERE_CENTER).norm(dim=-1)
    # The hull of 6 perspective views exceeds the sphere by under 5% of r (the corners between the
    # silhouette cones); carving at voxel centres and the jitter add up to ~1.4 voxels.
    assert float(radii.max()) <= SPHERE_RADIUS + 2.0 * voxel
    # Surface voxels come first: the first num_surface points hug the surface (a surface voxel's centre
    # is within one voxel of the hull's boundary, plus the jitter and the hull's excess).
    assert float((radii[:num_surface] - SPHERE_RADIUS).abs().max()) <= 2.5 * voxel
    # The points cover the sphere: every point of its surface has a sampled point within ~1 voxel.
    surface = SPHERE_CENTER + SPHERE_RADIUS * _fibonacci_directions(400)
    assert float(torch.cdist(surface, points).min(dim=1).values.max()) <= math.sqrt(3.0) * voxel
    # Every point projects into (or within a pixel of) every silhouette.
    for view in range(len(AXES)):
        uv, _ = project_points(points, w2c[view], K[view])
        disc = masks[view].nonzero().float()[:, [1, 0]] + 0.5
        assert float(torch.cdist(uv, disc).min(dim=1).values.max()) <= 2.5


def test_visual_hull_with_two_views_still_contains_the_sphere():
    masks, w2c, K = _sphere_rig([(1, 0.2, 0.1), (-0.3, 1, 0.2)])
    hull = carve_visual_hull(masks, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=32)
    _assert_contains_sphere(hull)
    channel_last = carve_visual_hull(masks[..., None], w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=32)
    assert torch.equal(channel_last.occupied, hull.occupied)
    points = visual_hull_points(masks, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=32, num_points=500)
    assert points.shape == (500, 3)
    assert float((points - BOUNDS_CENTER).norm(dim=-1).max()) <= BOUNDS_RADIUS + hull.voxel_size


def test_views_that_do_not_see_a_voxel_do_not_carve_it():
    masks, w2c, K = _sphere_rig(AXES)
    reference = carve_visual_hull(
        masks, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=24, min_views_fraction=0.0
    )
    # A seventh camera that looks away from the object with an empty mask carves nothing.
    away = opengl_c2w_to_opencv_w2c(
        look_at_opengl_c2w(torch.tensor([3.0, 0.0, 0.0]), torch.tensor([6.0, 0.0, 0.0]))
    ).float()
    hull = carve_visual_hull(
        torch.cat([masks, torch.zeros_like(masks[:1])]),
        torch.cat([w2c, away[None]]),
        torch.cat([K, K[:1]]),
        BOUNDS_CENTER,
        BOUNDS_RADIUS,
        resolution=24,
        min_views_fraction=0.0,
    )
    assert torch.equal(hull.occupied, reference.occupied)


def test_voxels_seen_by_too_few_views_are_dropped():
    # Narrow fields of view: most of the bounding sphere is outside both images.
    masks, w2c, K = _sphere_rig([(1, 0.2, 0.1), (-0.3, 1, 0.2)], fov_factor=0.4)
    hull = carve_visual_hull(
        masks, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=24, min_views_fraction=0.5
    )
    points = hull.centers(hull.occupied.nonzero())
    assert points.shape[0] > 0
    height, width = masks.shape[1:]
    seen_by = torch.zeros(points.shape[0], dtype=torch.int64)
    for view in range(2):
        uv, z = project_points(points, w2c[view], K[view])
        inside = (z > 0) & (uv >= 0).all(-1) & (uv[:, 0] <= width) & (uv[:, 1] <= height)
        seen_by += inside.long()
    assert int(seen_by.min()) >= 1
    both = carve_visual_hull(
        masks, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=24, min_views_fraction=1.0
    )
    assert int(both.occupied.sum()) < int(hull.occupied.sum())
    assert bool(hull.occupied[both.occupied].all())


def test_mask_tolerance_survives_one_bad_mask():
    masks, w2c, K = _sphere_rig(AXES)
    reference = carve_visual_hull(masks, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=24)
    broken = masks.clone()
    broken[2] = 0.0
    strict = carve_visual_hull(broken, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=24)
    tolerant = carve_visual_hull(
        broken, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=24, mask_tolerance_views=1
    )
    assert int(strict.occupied.sum()) == 0
    assert bool(tolerant.occupied[reference.occupied].all())
    assert int(tolerant.occupied.sum()) >= int(reference.occupied.sum())


def test_visual_hull_points_are_deterministic_under_a_seed():
    masks, w2c, K = _sphere_rig(AXES[:3])

    def sample(seed: int) -> torch.Tensor:
        generator = torch.Generator().manual_seed(seed)
        return visual_hull_points(
            masks, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=24, num_points=300, generator=generator
        )

    assert torch.equal(sample(5), sample(5))
    assert not torch.equal(sample(5), sample(6))


def test_empty_hull_raises_and_initial_points_falls_back(caplog):
    masks, w2c, K = _sphere_rig(AXES[:2])
    empty = torch.zeros_like(masks)
    with pytest.raises(EmptyVisualHullError, match="visual hull is empty"):
        visual_hull_points(empty, w2c, K, BOUNDS_CENTER, BOUNDS_RADIUS, resolution=16)
    generator = torch.Generator().manual_seed(0)
    with caplog.at_level(logging.WARNING, logger="diamond_sss.gaussians.init"):
        result = initial_points(
            num_points=200,
            bounds_center=BOUNDS_CENTER,
            bounds_radius=BOUNDS_RADIUS,
            masks=empty,
            w2c=w2c,
            K=K,
            hull_resolution=16,
            generator=generator,
        )
    assert result.source == "random" and result.points.shape == (200, 3)
    assert "visual hull is empty" in caplog.text
    hull = initial_points(
        num_points=200, bounds_center=BOUNDS_CENTER, bounds_radius=BOUNDS_RADIUS, masks=masks, w2c=w2c, K=K
    )
    assert hull.source == "visual_hull" and hull.points.shape == (200, 3)


def test_random_points_fill_the_ball_uniformly():
    points = random_points_in_sphere(SPHERE_CENTER, 2.0, 20000, torch.Generator().manual_seed(0))
    radii = (points - SPHERE_CENTER).norm(dim=-1)
    assert float(radii.max()) <= 2.0
    # Uniform in volume: P(|x| <= r) = (r / R)^3; the mean offset vanishes.
    assert abs(float((radii <= 1.0).float().mean()) - 0.125) < 0.01
    assert float((points.mean(dim=0) - SPHERE_CENTER).norm()) < 0.05
    again = random_points_in_sphere(SPHERE_CENTER, 2.0, 20000, torch.Generator().manual_seed(0))
    assert torch.equal(points, again)


def _write_vertex_ply(path, columns: dict[str, np.ndarray]) -> None:
    dtype = [(name, values.dtype.str) for name, values in columns.items()]
    vertices = np.empty(len(next(iter(columns.values()))), dtype=dtype)
    for name, values in columns.items():
        vertices[name] = values
    PlyData([PlyElement.describe(vertices, "vertex")]).write(str(path))


def test_load_points3d_ply(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(10, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, size=(10, 3)).astype(np.uint8)
    columns = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    columns |= {
        "nx": np.zeros(10, np.float32),
        "ny": np.zeros(10, np.float32),
        "nz": np.zeros(10, np.float32),
    }
    columns |= {"red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]}
    _write_vertex_ply(tmp_path / "points3d.ply", columns)
    points, colors, normals = load_points3d_ply(tmp_path / "points3d.ply")
    assert torch.equal(points, torch.from_numpy(xyz))
    torch.testing.assert_close(colors, srgb_to_linear(torch.from_numpy(rgb.astype(np.float32) / 255.0)))
    assert normals is None  # all-zero normals mean "no normals"

    columns["nx"] = np.ones(10, np.float32)
    _write_vertex_ply(tmp_path / "with_normals.ply", columns)
    _, _, normals = load_points3d_ply(tmp_path / "with_normals.ply")
    assert normals is not None and torch.equal(normals[:, 0], torch.ones(10))

    del columns["z"]
    _write_vertex_ply(tmp_path / "broken.ply", columns)
    with pytest.raises(ValueError, match=r"broken\.ply.*'z'"):
        load_points3d_ply(tmp_path / "broken.ply")
    result = initial_points(
        num_points=5,
        bounds_center=SPHERE_CENTER,
        bounds_radius=1.0,
        points3d_path=tmp_path / "with_normals.ply",
    )
    assert result.source == "points3d" and result.points.shape == (10, 3)


# ------------------------------------------------------------------------------------------------- PLY


def test_ply_round_trip_is_exact_and_standard_fields_decode_to_base_color(tmp_path):
    model = _random_model(33)
    path = export_ply(model, tmp_path / "nested" / "gaussians.ply")
    assert sorted(p.name for p in path.parent.iterdir()) == ["gaussians.ply"]  # no temporary file left
    loaded = import_ply(path)
    for name in PARAM_SHAPES:
        assert torch.equal(loaded.params[name], model.params[name]), name

    vertex = PlyData.read(str(path))["vertex"]
    names = [prop.name for prop in vertex.properties]
    standard = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    standard += [f"f_rest_{i}" for i in range(45)] + ["opacity", "scale_0", "scale_1", "scale_2"]
    standard += ["rot_0", "rot_1", "rot_2", "rot_3"]
    assert names[: len(standard)] == standard
    extra = ["base_color_0", "base_color_1", "base_color_2", "roughness", "metallic", "subsurface"]
    assert names[len(standard) :] == extra + [f"vis_sh_{i}" for i in range(16)]
    f_dc = torch.from_numpy(np.stack([vertex[f"f_dc_{i}"] for i in range(3)], axis=-1))
    torch.testing.assert_close(SH_C0 * f_dc + 0.5, model.base_color.detach())
    assert all(float(np.abs(vertex[f"f_rest_{i}"]).max()) == 0.0 for i in range(45))
    torch.testing.assert_close(torch.from_numpy(vertex["opacity"].copy()), model.params["opacities"].detach())


def test_import_ply_names_the_missing_property(tmp_path):
    columns = {name: np.zeros(3, np.float32) for name in ("x", "y", "z", "opacity")}
    _write_vertex_ply(tmp_path / "plain.ply", columns)
    with pytest.raises(ValueError, match=r"plain\.ply.*'nx'"):
        import_ply(tmp_path / "plain.ply")


def test_one_list_of_gaussian_parameters_gives_shapes_ply_fields_and_learning_rates():
    from dataclasses import fields

    from diamond_sss.gaussians.model import GAUSSIAN_PARAMS
    from diamond_sss.training.config import LearningRates
    from diamond_sss.training.trainer import GAUSSIAN_LR_KEYS

    assert list(PARAM_SHAPES) == [param.name for param in GAUSSIAN_PARAMS]
    names = [name for param in GAUSSIAN_PARAMS for name in param.ply]
    assert len(names) == len(set(names)) == 3 + 3 + 4 + 1 + 3 + 3 + 1 + 1 + 1 + NUM_VISIBILITY_SH
    for param in GAUSSIAN_PARAMS:
        assert len(param.ply) == math.prod(param.shape), param.name
    assert list(GAUSSIAN_LR_KEYS) == [name for name in PARAM_SHAPES if name != "means"]
    assert set(GAUSSIAN_LR_KEYS.values()) <= {f.name for f in fields(LearningRates)}
