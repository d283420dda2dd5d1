"""Synthetic OLAT data: shapes, materials, light stage, writer and tiny Mitsuba renders."""

from __future__ import annotations

import importlib.util
import json
import math
import re
from dataclasses import replace
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from diamond_sss.cli.synth_commands import synth
from diamond_sss.data.conventions import (
    intrinsics_from_fov,
    opengl_c2w_to_opencv_w2c,
    pixel_grid,
    project_points,
    unproject_pixels,
)
from diamond_sss.synth.materials import TranslucentMaterial, get_material, material_names
from diamond_sss.synth.render import (
    OlatRenderer,
    RenderSettings,
    SynthConfig,
    compute_exposure,
    image_seed,
    parse_subset,
    plan_pairs,
    synthesize,
)
from diamond_sss.synth.scene import (
    LightStageConfig,
    build_light_stage,
    interleaved_test_indices,
    view_light_subsets,
)
from diamond_sss.synth.shapes import (
    build_shape,
    knot_field,
    marching_tetrahedra,
    shape_names,
    sphere_field,
    trefoil_curve,
)
from diamond_sss.synth.writer import FrameRecord, encode_rgba8, write_json, write_png, write_transforms

needs_mitsuba = pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="needs mitsuba")


def _edges(faces: np.ndarray) -> np.ndarray:
    return np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    tri = vertices.astype(np.float64)[faces]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


# ----------------------------------------------------------------------------------------------- shapes


@pytest.mark.parametrize("name", ["sphere", "torus", "blob", "bunny", "bust", "knot"])
def test_shapes_are_closed_oriented_and_fit_the_unit_sphere(name):
    mesh = build_shape(name, seed=3, resolution=40)
    directed = _edges(mesh.faces)
    assert len(np.unique(directed, axis=0)) == len(directed), "inconsistent face orientation"
    _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert (counts == 2).all(), "mesh is not watertight"
    assert _signed_volume(mesh.vertices, mesh.faces) > 0.0, "faces do not point outward"
    assert np.linalg.norm(mesh.vertices, axis=1).max() == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-4)


def test_marching_tetrahedra_sphere_matches_analytic_radius_and_volume():
    radius = 0.8
    mesh = marching_tetrahedra(sphere_field((0.0, 0.0, 0.0), radius), resolution=32, bound=1.0)
    np.testing.assert_allclose(np.linalg.norm(mesh.vertices, axis=1), radius, atol=2e-3)
    assert _signed_volume(mesh.vertices, mesh.faces) == pytest.approx(
        4.0 / 3.0 * math.pi * radius**3, rel=0.02
    )
    np.testing.assert_allclose(mesh.normals, mesh.vertices / radius, atol=5e-3)


def test_shapes_deterministic_under_seed_and_blob_depends_on_it():
    a, b = build_shape("blob", seed=7, resolution=24), build_shape("blob", seed=7, resolution=24)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    c = build_shape("blob", seed=8, resolution=24)
    assert a.vertices.shape != c.vertices.shape or not np.allclose(a.vertices, c.vertices)


def test_knot_is_a_trefoil_tube_of_genus_one():
    """The tube around a knot is a torus: Euler characteristic V - E + F = 0 (a sphere's is 2); the field is the
    distance to the curve less the tube radius, so curve points lie ``scale * tube`` deep inside."""
    np.testing.assert_allclose(trefoil_curve(np.array([0.0, np.pi / 2])), [[0.0, -1.0, 0.0], [1.0, 2.0, 1.0]],
                               atol=1e-12)
    field = knot_field(scale=0.3, tube=0.45)
    on_curve = 0.3 * trefoil_curve(np.linspace(0.0, 2.0 * np.pi, 50))
    np.testing.assert_allclose(field(on_curve), -0.3 * 0.45, atol=1e-3)
    assert field(np.zeros((1, 3)))[0] > 0.0, "the knot's centre is a hole"
    for name, euler in (("knot", 0), ("sphere", 2)):
        mesh = build_shape(name, resolution=40)
        edges = np.unique(np.sort(_edges(mesh.faces), axis=1), axis=0)
        assert len(mesh.vertices) - len(edges) + len(mesh.faces) == euler, name


def test_shape_registry_and_errors():
    assert {"sphere", "torus", "blob", "bunny", "bust", "knot"} <= set(shape_names())
    with pytest.raises(ValueError, match="valid shapes: .*bunny"):
        build_shape("teapot")
    with pytest.raises(ValueError, match="resolution"):
        marching_tetrahedra(sphere_field((0, 0, 0), 0.5), resolution=2, bound=1.0)
    with pytest.raises(ValueError, match="grid boundary"):
        marching_tetrahedra(sphere_field((0, 0, 0), 2.0), resolution=8, bound=1.0)


# -------------------------------------------------------------------------------------------- materials


def test_material_registry_and_validation():
    assert {"wax", "jade", "marble", "skin", "soap"} <= set(material_names())
    for name in material_names():
        material = get_material(name)
        medium = material.medium_dict()
        recovered = [v * medium["scale"] for v in medium["sigma_t"]["value"]]
        np.testing.assert_allclose(recovered, material.sigma_t)
        assert max(medium["sigma_t"]["value"]) == pytest.approx(1.0)
        assert material.bsdf_dict()["type"] in ("null", "roughdielectric")
    with pytest.raises(ValueError, match="valid materials: .*wax"):
        get_material("chocolate")
    wax = get_material("wax")
    with pytest.raises(ValueError, match="roughness >= 0.05"):
        replace(wax, boundary="roughdielectric", roughness=0.01)
    with pytest.raises(ValueError, match="boundary"):
        replace(wax, boundary="dielectric")
    with pytest.raises(ValueError, match="albedo"):
        TranslucentMaterial("bad", albedo=(1.2, 0.5, 0.5), sigma_t=(1.0, 1.0, 1.0), g=0.0)
    with pytest.raises(ValueError, match="sigma_t"):
        TranslucentMaterial("bad", albedo=(0.5, 0.5, 0.5), sigma_t=(0.0, 1.0, 1.0), g=0.0)


# ---------------------------------------------------------------------------------------------- stage


def test_light_stage_test_split_is_novel_and_cameras_aim_at_origin():
    config = LightStageConfig(views=12, lights=10, test_views=4, test_lights=3, seed=5)
    stage = build_light_stage(config)
    assert stage.train_c2w.shape == (12, 4, 4) and stage.test_c2w.shape == (4, 4, 4)
    assert stage.train_lights.shape == (10, 3) and stage.test_lights.shape == (3, 3)
    for train, test, radius in (
        (stage.train_c2w[:, :3, 3], stage.test_c2w[:, :3, 3], config.camera_radius),
        (stage.train_lights, stage.test_lights, config.light_radius),
    ):
        np.testing.assert_allclose(np.linalg.norm(np.concatenate([train, test]), axis=1), radius, rtol=1e-9)
        gaps = np.linalg.norm(train[:, None] - test[None], axis=-1)
        assert gaps.min() > 0.05 * radius, "a test position coincides with a training position"
    size = 32
    K = intrinsics_from_fov(stage.fov_x, size, size).double()
    w2c = opengl_c2w_to_opencv_w2c(torch.from_numpy(np.concatenate([stage.train_c2w, stage.test_c2w])))
    uv, z = project_points(torch.zeros(len(w2c), 1, 3, dtype=torch.float64), w2c, K)
    np.testing.assert_allclose(uv.squeeze(1).numpy(), size / 2.0, atol=1e-9)
    np.testing.assert_allclose(z.numpy(), config.camera_radius, rtol=1e-9)
    again = build_light_stage(config)
    np.testing.assert_array_equal(again.train_c2w, stage.train_c2w)
    other = build_light_stage(replace(config, seed=6))
    assert not np.allclose(other.train_lights, stage.train_lights)


def test_interleaved_test_indices_and_subset_selection():
    np.testing.assert_array_equal(interleaved_test_indices(10, 2), [2, 7])
    assert interleaved_test_indices(5, 0).size == 0
    selected = parse_subset("relight:3x10,novelview:10x3", views=40, lights=24)
    assert len(selected["relight"]) == 30 and len(selected["novelview"]) == 30
    assert len({v for v, _ in selected["relight"]}) == 3 and len({l for _, l in selected["novelview"]}) == 3
    union = {p for pairs in selected.values() for p in pairs}
    assert len(union) <= 0.07 * 40 * 24
    for bad in ("relight:3", "spin:2x2", "relight:50x2", ""):
        with pytest.raises(ValueError):
            parse_subset(bad, views=40, lights=24)


def test_lights_per_view_plans_an_incomplete_lattice():
    stage = LightStageConfig(views=10, lights=8, test_views=3, test_lights=2, lights_per_view=3, seed=4)
    config = SynthConfig(shape="sphere", material="wax", out=Path("unused"), stage=stage, seed=4)
    pairs = plan_pairs(config)
    lights_of = {v: [l for view, l in pairs["train"] if view == v] for v in range(10)}
    assert all(len(lights) == len(set(lights)) == 3 for lights in lights_of.values())
    assert all(0 <= l < 8 for lights in lights_of.values() for l in lights)
    assert len({tuple(lights) for lights in lights_of.values()}) > 1, "every view got the same lights"
    assert plan_pairs(config) == pairs
    assert plan_pairs(replace(config, stage=replace(stage, seed=5)))["train"] != pairs["train"]
    assert pairs["test"] == [(v, l) for v in range(3) for l in range(2)], "the test split stays complete"
    assert view_light_subsets(replace(stage, lights_per_view=None)) == [list(range(8))] * 10
    assert len(plan_pairs(replace(config, stage=replace(stage, lights_per_view=8)))["train"]) == 80
    # a subset of the incomplete lattice: captured pairs pass, an uncaptured one is named
    captured = pairs["train"][4]
    missing = next((v, l) for v in range(10) for l in range(8) if (v, l) not in pairs["train"])
    subset = f"pair:{captured[0]}/{captured[1]}"
    assert plan_pairs(replace(config, subset=subset))["train"] == [captured]
    with pytest.raises(ValueError, match=rf"pairs \[{re.escape(str(missing))}\] .*lights_per_view=3 leaves uncaptured"):
        plan_pairs(replace(config, subset=f"{subset},pair:{missing[0]}/{missing[1]}"))
    for bad in (0, 9):
        with pytest.raises(ValueError, match="lights_per_view must be in 1..8"):
            replace(stage, lights_per_view=bad)


def test_height_bands_bound_cameras_and_lights():
    """A camera cap stopping 30 degrees below the horizon (z/r >= -0.5) and lights on the full sphere."""
    config = LightStageConfig(views=40, lights=24, camera_radius=3.2, light_radius=4.5,
                              camera_band=(-0.5, 0.95), light_band=(-1.0, 1.0), seed=21)
    stage = build_light_stage(config)
    eyes = np.concatenate([stage.train_c2w[:, :3, 3], stage.test_c2w[:, :3, 3]])
    heights = eyes[:, 2] / np.linalg.norm(eyes, axis=1)
    assert heights.min() >= -0.5 and heights.max() <= 0.95
    assert heights.min() < -0.45 and heights.max() > 0.9, "the band is not spanned"
    lights = np.concatenate([stage.train_lights, stage.test_lights])
    np.testing.assert_allclose(np.linalg.norm(lights, axis=1), 4.5, rtol=1e-9)
    assert lights[:, 2].min() < -0.9 * 4.5 and lights[:, 2].max() > 0.9 * 4.5
    with pytest.raises(ValueError, match="height band"):
        replace(config, camera_band=(0.5, -0.5))


def test_pair_subset_terms():
    assert parse_subset("pair:3/5,pair:0/0", views=4, lights=6) == {"pair": [(3, 5), (0, 0)]}
    for bad in ("pair:4/0", "pair:0/6", "pair:1-2", "pair:a/1"):
        with pytest.raises(ValueError, match="pair"):
            parse_subset(bad, views=4, lights=6)


# --------------------------------------------------------------------------------------------- writer


def test_encode_rgba8_known_values():
    image = np.zeros((1, 3, 4), dtype=np.float32)
    image[0, 0] = [0.001, 0.5, 2.0, 1.0]
    image[0, 1] = [0.25, 0.25, 0.25, 0.5]
    out = encode_rgba8(image, exposure=2.0)
    expected_mid = round(255 * (1.055 * 0.5 ** (1 / 2.4) - 0.055))
    assert out[0, 0].tolist() == [round(255 * 12.92 * 0.002), 255, 255, 255]
    assert out[0, 1].tolist() == [expected_mid] * 3 + [128]
    assert out[0, 2].tolist() == [0, 0, 0, 0]
    with pytest.raises(ValueError, match="RGBA"):
        encode_rgba8(np.zeros((2, 2, 3)), 1.0)


def test_writers_are_atomic_and_round_trip(tmp_path):
    rgba = np.random.default_rng(0).integers(0, 256, size=(5, 7, 4), dtype=np.uint8)
    write_png(tmp_path / "a" / "img.png", rgba)
    np.testing.assert_array_equal(iio.imread(tmp_path / "a" / "img.png"), rgba)
    write_json(tmp_path / "meta.json", {"x": 1})
    write_json(tmp_path / "meta.json", {"x": 2})
    assert json.loads((tmp_path / "meta.json").read_text()) == {"x": 2}
    frame = FrameRecord(c2w=np.eye(4), depth_path="train/v000_depth.npy")
    frame.file_paths.append("train/v000_l000.png")
    frame.light_positions.append([1.0, 2.0, 3.0])
    frame.light_intensities.append([1.0, 1.0, 1.0])
    path = write_transforms(tmp_path, "train", 0.5, 7, 5, [frame])
    payload = json.loads(path.read_text())
    assert payload["camera_angle_x"] == 0.5 and payload["w"] == 7 and payload["h"] == 5
    assert payload["premultiplied_alpha"] is True  # the renders' alpha is a separate coverage pass
    assert payload["frames"][0]["depth_path"] == "train/v000_depth.npy"
    assert "normal_path" not in payload["frames"][0]
    leftovers = [p.name for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]
    assert leftovers == []
    with pytest.raises(ValueError, match="uint8"):
        write_png(tmp_path / "bad.png", rgba.astype(np.float32))


def test_image_seeds_are_distinct_and_reproducible():
    seeds = {image_seed(0, split, v, l) for split in ("train", "test") for v in range(4) for l in range(4)}
    assert len(seeds) == 32
    assert image_seed(3, "train", 1, 2) == image_seed(3, "train", 1, 2) != image_seed(4, "train", 1, 2)


# ------------------------------------------------------------------------------------- Mitsuba renders


@pytest.fixture(scope="module")
def tiny_renderer():
    if importlib.util.find_spec("mitsuba") is None:
        pytest.skip("needs mitsuba")
    mesh = build_shape("blob", seed=1, resolution=32)
    settings = RenderSettings(width=16, height=16, spp=8, geometry_spp=8, fov_x=math.radians(40.0))
    return mesh, OlatRenderer(mesh, get_material("wax"), settings)


def _front_lit(config: LightStageConfig):
    stage = build_light_stage(config)
    eye = stage.train_c2w[0, :3, 3]
    light = stage.train_lights[np.argmax(stage.train_lights @ eye)]
    return stage, light


def test_tiny_render_mask_exposure_and_determinism(tiny_renderer):
    _, renderer = tiny_renderer
    stage, light = _front_lit(LightStageConfig(views=3, lights=6, fov_x_deg=40.0))
    image = renderer.render(stage.train_c2w[0], light, seed=11)
    again = renderer.render(stage.train_c2w[0], light, seed=11)
    np.testing.assert_array_equal(image, again)
    assert not np.array_equal(image, renderer.render(stage.train_c2w[0], light, seed=12))
    alpha, depth, normal = renderer.render_geometry(stage.train_c2w[0])
    assert alpha[7:9, 7:9].min() == 1.0, "object missing from the image centre"
    border = np.concatenate([alpha[0], alpha[-1], alpha[:, 0], alpha[:, -1]])
    assert border.max() == 0.0, "object touches the image border"
    assert (image[[0, -1]][..., :3] == 0).all() and (image[:, [0, -1]][..., :3] == 0).all(), "background lit"
    exposure = compute_exposure(renderer, stage.train_c2w, stage.train_lights, object_seed=0)
    exposed = encode_rgba8(image, exposure)[..., :3][alpha == 1] / 255.0
    assert 0.1 < np.median(exposed) < 0.9, f"badly exposed: median sRGB {np.median(exposed):.3f}"
    assert (exposed >= 1.0).mean() < 0.2, "exposure saturates the object"
    assert (depth[alpha == 0] == 0).all() and (normal[alpha == 0] == 0).all()


def test_depth_and_normal_maps_follow_project_conventions(tiny_renderer):
    mesh, renderer = tiny_renderer
    stage = build_light_stage(LightStageConfig(views=3, lights=2, fov_x_deg=40.0, seed=2))
    K = intrinsics_from_fov(stage.fov_x, 16, 16).double()
    for c2w in stage.train_c2w:
        alpha, depth, normal = renderer.render_geometry(c2w)
        inner = alpha == 1.0
        w2c = opengl_c2w_to_opencv_w2c(torch.from_numpy(c2w))
        uv = pixel_grid(16, 16).double()[torch.from_numpy(inner)]
        points = unproject_pixels(uv, torch.from_numpy(depth[inner]).double(), w2c, K).numpy()
        gaps = np.linalg.norm(points[:, None] - mesh.vertices[None], axis=-1)
        nearest = gaps.argmin(axis=1)
        assert np.median(gaps.min(axis=1)) < 0.035, "depth map does not land on the mesh surface"
        cosines = (normal[inner] * mesh.normals[nearest]).sum(axis=-1)
        assert np.median(cosines) > 0.97, "normal map disagrees with the mesh normals"
        view_dir = points - c2w[:3, 3]
        assert ((normal[inner] * view_dir).sum(axis=-1) < 0).mean() > 0.9, "normals face away from camera"


@needs_mitsuba
def test_rough_dielectric_boundary_is_not_black():
    mesh = build_shape("sphere", resolution=16)
    renderer = OlatRenderer(mesh, get_material("glazed_wax"), RenderSettings(width=8, height=8, spp=16))
    stage, light = _front_lit(LightStageConfig(views=2, lights=6))
    image = renderer.render(stage.train_c2w[0], light, seed=0)
    assert image[3:5, 3:5, :3].max() > 0.0


@needs_mitsuba
def test_synthesize_writes_the_olat_format(tmp_path):
    stage = LightStageConfig(views=2, lights=2, test_views=1, test_lights=1, fov_x_deg=40.0)
    config = SynthConfig(
        shape="blob", material="soap", out=tmp_path, stage=stage, size=16, spp=4, seed=0, mesh_resolution=24
    )
    count = []
    meta = synthesize(config, on_image=lambda: count.append(1))
    assert len(count) == sum(len(p) for p in plan_pairs(config).values()) == 5
    saved = json.loads((tmp_path / "meta.json").read_text())
    for key in (
        "shape",
        "material",
        "seed",
        "spp",
        "exposure",
        "stage",
        "lights",
        "cameras",
        "pairs",
        "mitsuba_variant",
        "render_seconds",
    ):
        assert key in saved
    assert saved["exposure"] == meta["exposure"] > 0
    poses, light_sets = {}, {}
    for split in ("train", "test"):
        payload = json.loads((tmp_path / f"transforms_{split}.json").read_text())
        assert payload["w"] == payload["h"] == 16 and payload["camera_angle_x"] == pytest.approx(
            math.radians(40)
        )
        poses[split] = [np.array(f["transform_matrix"]) for f in payload["frames"]]
        light_sets[split] = [p for f in payload["frames"] for p in f["light_positions"]]
        for frame in payload["frames"]:
            assert (
                len(frame["file_paths"]) == len(frame["light_positions"]) == len(frame["light_intensities"])
            )
            for rel in frame["file_paths"]:
                assert rel.startswith(f"{split}/") and rel.endswith(".png")
                png = iio.imread(tmp_path / rel)
                assert png.shape == (16, 16, 4) and png.dtype == np.uint8
                assert png[0, 0, 3] == 0 and png[8, 8, 3] == 255
                assert (png[..., :3][png[..., 3] == 0] == 0).all()
            depth = np.load(tmp_path / frame["depth_path"], allow_pickle=False)
            normal = np.load(tmp_path / frame["normal_path"], allow_pickle=False)
            assert depth.shape == (16, 16) and depth.dtype == np.float32 and normal.shape == (16, 16, 3)
            assert depth.max() > 0 and depth[0, 0] == 0
    for test_pose in poses["test"]:
        assert all(not np.allclose(test_pose, p) for p in poses["train"])
    for test_light in light_sets["test"]:
        assert all(not np.allclose(test_light, p) for p in light_sets["train"])


@needs_mitsuba
def test_cross_splits_pair_test_cameras_with_training_lights_and_back(tmp_path):
    stage = LightStageConfig(views=4, lights=3, test_views=2, test_lights=1, fov_x_deg=40.0)
    config = SynthConfig(shape="blob", material="soap", out=tmp_path, stage=stage, size=16, spp=4, seed=0,
                         mesh_resolution=24, train=False, cross_splits=True)
    pairs = plan_pairs(config)
    # the 2 test views under the middle training light; training views 1 and 3 (spread) under the test light
    assert pairs == {"train": [], "test": [(0, 0), (1, 0)], "novel_view": [(0, 1), (1, 1)],
                     "novel_light": [(1, 0), (3, 0)]}
    assert plan_pairs(replace(config, cross_splits=False)) == {"train": [], "test": [(0, 0), (1, 0)]}
    synthesize(config)
    saved = json.loads((tmp_path / "meta.json").read_text())
    rig = {kind: {split: np.array(saved[kind][split]) for split in ("train", "test")} for kind in ("cameras", "lights")}
    for split, (camera_set, light_set) in (("novel_view", ("test", "train")), ("novel_light", ("train", "test"))):
        frames = json.loads((tmp_path / f"transforms_{split}.json").read_text())["frames"]
        for frame, view in zip(frames, sorted({v for v, _ in pairs[split]}), strict=True):
            np.testing.assert_allclose(frame["transform_matrix"], rig["cameras"][camera_set][view])
            lights = [light for v, light in pairs[split] if v == view]
            np.testing.assert_allclose(frame["light_positions"], rig["lights"][light_set][lights])
            assert all(rel.startswith(f"{split}/") for rel in frame["file_paths"])
    assert image_seed(0, "novel_view", 0, 1) != image_seed(0, "novel_light", 0, 1) != image_seed(0, "test", 0, 1)


@needs_mitsuba
def test_cli_renders_another_rig_with_an_incomplete_lattice(tmp_path):
    from diamond_sss.cli.main import main

    main(["synth", "--shape", "sphere", "--material", "wax", "--out", str(tmp_path), "--views", "3", "--lights",
          "4", "--lights-per-view", "2", "--test-views", "1", "--test-lights", "1", "--size", "8", "--spp", "2",
          "--camera-radius", "3.2", "--fov-x-deg", "40", "--camera-band", "-0.5", "0.95", "--light-band", "-1", "1",
          "--light-radius", "4.5", "--seed", "21"])
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["lights_per_view"] == meta["stage"]["lights_per_view"] == 2
    assert meta["stage"]["camera_band"] == [-0.5, 0.95] and meta["stage"]["light_band"] == [-1.0, 1.0]
    frames = json.loads((tmp_path / "transforms_train.json").read_text())["frames"]
    assert [len(f["file_paths"]) for f in frames] == [2, 2, 2]
    planned = [[v, l] for v, lights in enumerate(view_light_subsets(LightStageConfig(
        views=3, lights=4, lights_per_view=2, seed=21))) for l in lights]
    assert meta["pairs"]["train"] == planned
    lights = np.array(meta["lights"]["train"])
    for view, frame in enumerate(frames):
        np.testing.assert_allclose(frame["light_positions"], lights[[l for v, l in planned if v == view]])


def test_cli_rejects_unknown_names_with_the_valid_ones(tmp_path):
    with pytest.raises(ValueError, match="valid shapes: .*torus"):
        synth(shape="cube", material="wax", out=tmp_path)
    with pytest.raises(ValueError, match="valid materials: .*jade"):
        synth(shape="sphere", material="glass", out=tmp_path)
    assert not any(Path(tmp_path).iterdir())
