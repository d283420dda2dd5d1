"""The generation lattice of a capture of only its sparse images: cameras and lights placed around the real ones,
or a rig file's; the pipeline generates on it, and says why when it generates nothing."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from tiny_models import TINY_NVS, TINY_RELIGHT

from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import SPHERE_RADIUS, make_capture
from diamond_sss.data.conventions import look_at_opengl_c2w, mean_up_vector, project_points, world_to_camera
from diamond_sss.data.dataset import directions_from
from diamond_sss.data.images import read_image_array, write_png
from diamond_sss.diffusion.nvs.canonical import PRIOR_FRAME_FILL
from diamond_sss.diffusion.nvs.model import NVSConfig, NVSModel
from diamond_sss.diffusion.relight.config import RelightModelConfig
from diamond_sss.diffusion.relight.model import RelightDiffusion
from diamond_sss.errors import DataError
from diamond_sss.pipeline.rig import (
    ELEVATION_MARGIN_DEG,
    build_lattice,
    elevation_deg,
    framed_capture_lattice,
    framed_intrinsics,
    place_directions,
    sampled_rig,
    silhouette_radius,
    spread_away,
)
from diamond_sss.pipeline.run import PipelineConfig, checked_config, run_pipeline

TRAIN = {"num_gaussians": 200, "batch_size": 1, "lambda_lpips": 0.0, "iterations": 2, "raytrace_gaussians": 32,
         "mv_pixels_per_pair": 16, "log_every": 1, "device": "cpu"}


@pytest.fixture(scope="module")
def sparse(tmp_path_factory):
    """A capture of only its 9 images (3 views x 3 lights, nothing else declared), tiny random models."""
    data = tmp_path_factory.mktemp("sparse")
    make_capture(data, views=3, lights=3, size=16)
    torch.manual_seed(0)
    nvs = NVSModel(NVSConfig(**TINY_NVS)).save(tmp_path_factory.mktemp("nvs"))
    relight = RelightDiffusion.from_config(RelightModelConfig(**TINY_RELIGHT)).save(tmp_path_factory.mktemp("rl"))
    return data, nvs, relight, tmp_path_factory.mktemp("cache")


def test_spread_away_picks_the_farthest_candidates_from_what_is_fixed():
    candidates = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0.9, 0.1, 0]], dtype=torch.float64)
    fixed = torch.tensor([[1.0, 0, 0]], dtype=torch.float64)
    assert spread_away(candidates, fixed, 1) == [1]  # the opposite direction
    assert spread_away(candidates, fixed, 2) == [1, 2]  # then the one farthest from both
    assert spread_away(candidates, fixed, 0) == [] and len(spread_away(candidates, fixed, 9)) == 4


def test_up_and_elevation_of_upright_cameras():
    eyes = torch.tensor([[3.0, 0, 1.0], [0, 3.0, -0.5], [-3.0, 0.5, 0.0]], dtype=torch.float64)
    c2w = look_at_opengl_c2w(eyes, torch.zeros(3))
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    w2c = torch.linalg.inv(c2w @ flip)  # OpenCV world-to-camera
    assert torch.allclose(mean_up_vector(w2c), torch.tensor([0.0, 0, 1], dtype=torch.float64), atol=0.2)
    dirs = torch.nn.functional.normalize(eyes, dim=-1)
    expected = torch.rad2deg(torch.asin(eyes[:, 2] / eyes.norm(dim=-1)))
    assert torch.allclose(elevation_deg(dirs, torch.tensor([0.0, 0, 1])), expected, atol=1e-6)


def test_sampled_cameras_and_lights_sit_where_the_real_ones_could(sparse):
    capture = OLATDataset(sparse[0])
    cameras, lights = sampled_rig(capture, 5, 4)
    assert (len(cameras), len(lights)) == (5, 4)
    center = capture.bounds.center.double()
    up = mean_up_vector(capture.viewmats)
    real_dirs = directions_from(capture.camera_centers, capture.bounds.center).double()
    real_elev = elevation_deg(real_dirs, up)
    real_dist = (capture.camera_centers.double() - center).norm(dim=-1)
    for entry in cameras:
        c2w = torch.tensor(entry["transform_matrix"], dtype=torch.float64)
        eye = c2w[:3, 3]
        assert float(real_dist.min()) - 1e-6 <= float((eye - center).norm()) <= float(real_dist.max()) + 1e-6
        direction = (eye - center) / (eye - center).norm()
        elev = float(elevation_deg(direction[None], up)[0])
        assert real_elev.min() - ELEVATION_MARGIN_DEG - 0.5 <= elev <= real_elev.max() + ELEVATION_MARGIN_DEG + 0.5
        assert float((real_dirs @ direction).max()) < 0.999  # not a real view
        assert (entry["fl_x"], entry["w"], entry["h"]) == (float(capture.intrinsics[0, 0, 0]), 16, 16)
    lattice_dir = sparse[3] / "lattice_check"
    _, lattice = build_lattice(lattice_dir, sparse[0], "train", range(9), rig_file=None, views=5, lights=4)
    for view in range(3, 8):  # aimed at the centre: it projects to the image centre
        camera = lattice.cameras[view]
        uv, depth = project_points(center[None], camera.w2c.double(), camera.K.double())
        assert torch.allclose(uv[0], torch.tensor([8.0, 8.0], dtype=torch.float64), atol=1e-3) and depth[0] > 0
    light_dist = (capture.light_positions.double() - center).norm(dim=-1)
    for entry in lights:
        distance = float((torch.tensor(entry["position"], dtype=torch.float64) - center).norm())
        assert float(light_dist.min()) - 1e-6 <= distance <= float(light_dist.max()) + 1e-6


def test_the_lattice_keeps_the_real_indices_and_images(sparse, tmp_path):
    capture = OLATDataset(sparse[0])
    source, lattice = build_lattice(tmp_path, sparse[0], "train", [0, 4, 8], rig_file=None, views=4, lights=2)
    assert (lattice.num_views, lattice.num_lights, len(lattice)) == (7, 5, 3)
    assert (source.new_views, source.new_lights) == ((3, 4, 5, 6), (3, 4))
    assert torch.allclose(lattice.viewmats[:3], capture.viewmats, atol=1e-5)
    assert torch.allclose(lattice.light_positions[:3], capture.light_positions, atol=1e-5)
    assert [(o.view, o.light) for o in lattice.observations] == [(0, 0), (1, 1), (2, 2)]
    assert torch.equal(lattice.load(1).rgb, capture.load(4).rgb)


def _rig(tmp_path, capture: OLATDataset, eyes: list[list[float]], **camera_keys) -> str:
    c2w = look_at_opengl_c2w(torch.tensor(eyes, dtype=torch.float64), torch.zeros(3))
    cameras = [{"transform_matrix": m.tolist(), "camera_angle_x": 0.8, **camera_keys} for m in c2w]
    lights = [{"position": p.tolist()} for p in capture.light_positions] + [{"position": [0.0, 0.0, -4.0]}]
    path = tmp_path / "rig.json"
    path.write_text(json.dumps({"w": 16, "h": 16, "cameras": cameras, "lights": lights}))
    return str(path)


def test_a_rig_file_gives_the_new_cameras_and_lights(sparse, tmp_path):
    capture = OLATDataset(sparse[0])
    rig = _rig(tmp_path, capture, [[0.0, 3.0, 0.0], [0.0, -3.0, 0.5]])
    source, lattice = build_lattice(tmp_path / "out", sparse[0], "train", range(9), rig_file=rig, views=0, lights=0)
    assert (source.new_views, source.new_lights) == ((3, 4), (3,))
    assert torch.allclose(lattice.light_positions[3], torch.tensor([0.0, 0.0, -4.0]))
    assert torch.allclose(lattice.camera_centers[3], torch.tensor([0.0, 3.0, 0.0]), atol=1e-5)


def test_a_bad_rig_file_is_named_and_nothing_is_written(sparse, tmp_path):
    capture = OLATDataset(sparse[0])
    out = tmp_path / "out"
    rig = _rig(tmp_path, capture, [[0.0, 3.0, 0.0]], w=32, h=32)
    with pytest.raises(DataError, match=r"rig .*rig\.json: cameras\[0\]: image size 32x32 \(w/h\) contradicts the "
                                        r"capture's 16x16"):
        build_lattice(out, sparse[0], "train", range(9), rig_file=rig, views=0, lights=0)
    real_pose = torch.linalg.inv(capture.viewmats[0].double())[:3, 3].tolist()
    rig = _rig(tmp_path, capture, [real_pose])  # a real camera's place with another field of view
    with pytest.raises(DataError, match=r"cameras\[0\]: at view 0's place but its intrinsics"):
        build_lattice(out, sparse[0], "train", range(9), rig_file=rig, views=0, lights=0)
    c2w = look_at_opengl_c2w(torch.tensor([0.0, 3.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 6.0, 0.0]))
    (tmp_path / "away.json").write_text(json.dumps({"w": 16, "h": 16, "lights": [{"position": [0, 0, 4]}],
                                                    "cameras": [{"transform_matrix": c2w.tolist(),
                                                                 "camera_angle_x": 0.8}]}))
    with pytest.raises(DataError, match=r"away\.json: new camera 0 \(lattice view 3\) cannot see the object"):
        build_lattice(out, sparse[0], "train", range(9), rig_file=str(tmp_path / "away.json"), views=0, lights=0)
    (tmp_path / "nolights.json").write_text(json.dumps({"cameras": [{"transform_matrix": c2w.tolist()}]}))
    with pytest.raises(DataError, match=r"nolights\.json: key 'lights': a rig file needs a non-empty list"):
        build_lattice(out, sparse[0], "train", range(9), rig_file=str(tmp_path / "nolights.json"), views=0, lights=0)
    assert not (out / "transforms_lattice.json").exists()


def test_the_pipeline_generates_on_a_capture_of_only_its_sparse_images(sparse, tmp_path):
    data, nvs, relight, cache = sparse
    cfg = PipelineConfig(rig_views=2, rig_lights=1, nvs_views=0, relight_lights=1, nvs_model=str(nvs),
                         relight_model=str(relight), nvs_steps=1, relight_steps=1, relight_samples=1,
                         min_silhouette_iou=0.0, min_mask_fraction=0.0, cache_dir=str(cache))
    result = run_pipeline(data, tmp_path, regime="all", overrides=TRAIN, config=cfg, show_progress=False)
    manifest = json.loads((tmp_path / "pipeline.json").read_text())
    assert manifest["inputs"]["lattice"] == "sampled"
    # the 2 placed cameras under each of the 3 real lights, then 5 views (3 real, 2 new) each relit to 1 light
    assert manifest["stages"]["nvs"]["targets"] == 2 and manifest["stages"]["nvs"]["calls"] >= 3
    assert manifest["stages"]["relight"]["images"] == 5
    assert result["synthetic_images"] == 11 and result["real_images"] == 9
    synthetic = OLATDataset(tmp_path / "synthetic", "train")
    assert (synthetic.num_views, synthetic.num_lights) == (5, 4)


def test_augmentation_that_generates_nothing_stops_with_the_reason(sparse, tmp_path):
    data, nvs, _, cache = sparse
    cfg = PipelineConfig(augment=("nvs",), rig_views=0, nvs_model=str(nvs), nvs_steps=1, cache_dir=str(cache))
    with pytest.raises(ValueError, match=r"--augment nvs generated no image \(nvs: every camera of the lattice .* has "
                                         r"a real image in the regime\); give a regime .*--rig FILE"):
        run_pipeline(data, tmp_path, regime="all", overrides=TRAIN, config=cfg, show_progress=False)
    assert not (tmp_path / "final").exists()


def test_a_one_image_capture_is_refused(tmp_path):
    make_capture(tmp_path, views=1, lights=1, size=16)
    with pytest.raises(DataError, match=r"transforms_train\.json: 1 image; a reconstruction needs at least 2"):
        run_pipeline(tmp_path, tmp_path / "run", regime="all", overrides=TRAIN,
                     config=PipelineConfig(augment=()), show_progress=False)
    assert not (tmp_path / "run" / "pipeline.json").exists()


def test_placed_directions_stay_within_the_angle_of_a_real_one():
    real = torch.nn.functional.normalize(torch.tensor([[1.0, 0, 0.2], [0, 1.0, 0.1], [-1.0, 0.2, 0.0]],
                                                       dtype=torch.float64), dim=-1)
    up = torch.tensor([0.0, 0, 1], dtype=torch.float64)
    anywhere, _ = place_directions(real, up, 6)
    near, nearest = place_directions(real, up, 6, max_angle_deg=25.0)
    closest = torch.rad2deg(torch.acos((near @ real.T).amax(dim=1).clamp(-1, 1)))
    assert len(near) == 6 and float(closest.max()) <= 25.0 + 1e-9 and float(closest.min()) > 5.0
    assert torch.equal(nearest, torch.argmax(near @ real.T, dim=1))
    assert float(torch.rad2deg(torch.acos((anywhere @ real.T).amax(dim=1).clamp(-1, 1))).max()) > 25.0


def test_the_silhouettes_give_the_spheres_radius(tmp_path):
    make_capture(tmp_path, views=3, lights=1, size=48)
    capture = OLATDataset(tmp_path)
    radius = silhouette_radius(capture, range(3), torch.zeros(3))
    assert SPHERE_RADIUS - 0.04 < radius < SPHERE_RADIUS + 0.01  # mask pixel centres: within half a pixel
    with pytest.raises(DataError, match=r"transforms_train\.json: every mask of the 0 images is empty"):
        silhouette_radius(capture, [], torch.zeros(3))


def _set_alpha(path, value: int) -> None:
    rgba = (read_image_array(path) * 255 + 0.5).astype(np.uint8)
    rgba[..., 3] = value
    write_png(path, rgba)


def test_a_cut_off_silhouette_is_named_and_empty_masks_stop_the_framing(tmp_path, caplog):
    make_capture(tmp_path, views=3, lights=1, size=32)
    _set_alpha(OLATDataset(tmp_path).observations[1].image_path, 255)  # the object fills view 1: cut off
    with caplog.at_level("WARNING", logger="diamond_sss.pipeline.rig"):
        silhouette_radius(OLATDataset(tmp_path), range(3), torch.zeros(3))
    assert "view 1's mask touches the image border" in caplog.text and "view 0's" not in caplog.text
    for obs in OLATDataset(tmp_path).observations:
        _set_alpha(obs.image_path, 0)
    with pytest.raises(DataError, match=r"transforms_train\.json: every mask of the 3 images is empty: no object "
                                        r"to frame .* use rig_framing=real"):
        silhouette_radius(OLATDataset(tmp_path), range(3), torch.zeros(3))


def test_auto_framing_follows_the_stages_and_a_rig_file_keeps_its_intrinsics(tmp_path):
    assert checked_config(PipelineConfig(augment=("repair",))).rig_framing == "prior"
    assert checked_config(PipelineConfig(augment=("nvs", "relight"))).rig_framing == "real"
    assert checked_config(PipelineConfig(augment=("repair",), rig=str(tmp_path / "rig.json"))).rig_framing == "real"
    with pytest.raises(ValueError, match=r"rig_framing' \(--rig-framing\) prior: the cameras of --rig .*rig\.json "
                                         r"keep the intrinsics the file gives"):
        checked_config(PipelineConfig(augment=("repair",), rig_framing="prior", rig=str(tmp_path / "rig.json")))


def test_framed_intrinsics_make_the_sphere_fill_the_priors_share_of_the_image():
    distance, radius, width, height = 5.0, 0.8, 96, 64
    K = framed_intrinsics(torch.tensor([0.0, 0.0, distance]), radius, width, height)
    w2c = torch.linalg.inv(look_at_opengl_c2w(torch.tensor([0.0, -distance, 0.0], dtype=torch.float64),
                                              torch.zeros(3, dtype=torch.float64))
                           @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64)))
    points = torch.nn.functional.normalize(torch.randn(200_000, 3, dtype=torch.float64), dim=-1) * radius
    uv, _ = project_points(points, w2c, K)
    extent = float((uv - torch.tensor([48.0, 32.0], dtype=torch.float64)).norm(dim=-1).max())
    assert extent == pytest.approx(PRIOR_FRAME_FILL * 32.0, rel=2e-3)  # the outline of the sphere's tangent cone
    off_axis = framed_intrinsics(torch.tensor([0.3, -0.2, 4.0]), radius, width, height)
    assert off_axis[0, 0] * 0.3 / 4.0 + off_axis[0, 2] == pytest.approx(48.0)  # the centre projects to the middle
    assert off_axis[1, 1] * -0.2 / 4.0 + off_axis[1, 2] == pytest.approx(32.0)
    with pytest.raises(ValueError, match="radius < distance"):
        framed_intrinsics(torch.tensor([0.0, 0.0, 1.0]), 1.0, 64, 64)


def test_placed_cameras_framed_as_the_priors_zoom_on_the_object(sparse):
    capture = OLATDataset(sparse[0])
    real, _ = sampled_rig(capture, 3, 0)
    framed, _ = sampled_rig(capture, 3, 0, framing="prior", observations=range(9))
    radius = silhouette_radius(capture, range(9), capture.bounds.center)
    for before, after in zip(real, framed, strict=True):
        assert before["transform_matrix"] == after["transform_matrix"] and (after["w"], after["h"]) == (16, 16)
        eye = torch.tensor(after["transform_matrix"], dtype=torch.float64)[:3, 3]
        distance = float((eye - capture.bounds.center.double()).norm())
        focal = PRIOR_FRAME_FILL * 8.0 / math.tan(math.asin(radius / distance))
        assert (after["fl_x"], after["fl_y"], after["cx"], after["cy"]) == pytest.approx((focal, focal, 8.0, 8.0))
        assert after["fl_x"] > 1.3 * before["fl_x"]  # the analytic sphere spans ~46% of the half-width
    with pytest.raises(ValueError, match="framing must be one of"):
        sampled_rig(capture, 3, 0, framing="zoomed")
    with pytest.raises(ValueError, match=r"'rig_framing' \(--rig-framing\) must be auto or one of real, prior, got 'zoomed'"):
        checked_config(PipelineConfig(rig_framing="zoomed"))


def test_the_capture_lattice_framed_zooms_only_the_cameras_without_an_image(tmp_path):
    make_capture(tmp_path / "capture", views=4, lights=2, size=24)
    capture = OLATDataset(tmp_path / "capture")
    chosen = [i for i, obs in enumerate(capture.observations) if obs.view in (0, 2)]
    source, lattice = framed_capture_lattice(tmp_path / "rig", tmp_path / "capture", "train", chosen)
    assert (lattice.num_views, lattice.num_lights, len(lattice)) == (4, 2, len(chosen))
    assert (source.new_views, source.new_lights) == ((), ())
    assert torch.allclose(lattice.viewmats, capture.viewmats, atol=1e-5)
    radius = silhouette_radius(capture, chosen, capture.bounds.center)
    for view in range(4):
        K, center = lattice.intrinsics[view].double(), capture.bounds.center.double()
        if view in (0, 2):
            assert torch.allclose(K, capture.intrinsics[view].double(), atol=1e-4)
            continue
        distance = float((capture.camera_centers[view].double() - center).norm())
        focal = PRIOR_FRAME_FILL * 12.0 / math.tan(math.asin(radius / distance))
        assert float(K[0, 0]) == pytest.approx(focal, rel=1e-5) and float(K[0, 0]) > 1.3 * capture.intrinsics[view, 0, 0]
        uv, _ = project_points(center[None], lattice.cameras[view].w2c.double(), K)
        assert torch.allclose(uv[0], torch.tensor([12.0, 12.0], dtype=torch.float64), atol=1e-3)
    for index, obs in zip(chosen, lattice.observations, strict=True):
        assert obs.image_path == capture.observations[index].image_path


@pytest.mark.parametrize("framing", ["prior", "real"])
def test_the_novel_view_prior_sees_its_references_framed_as_the_cameras_it_generates_at(sparse, tmp_path, monkeypatch,
                                                                                        framing):
    import diamond_sss.diffusion.nvs.pipeline as nvs_pipeline

    data, nvs, _, cache = sparse
    calls = []
    generate = nvs_pipeline.generate_novel_views
    monkeypatch.setattr(nvs_pipeline, "generate_novel_views",
                        lambda *args, **kwargs: calls.append((args[2], kwargs["reference_K"])) or generate(*args, **kwargs))
    cfg = PipelineConfig(augment=("nvs",), rig_views=2, rig_lights=1, nvs_views=0, nvs_model=str(nvs), nvs_steps=1,
                         min_silhouette_iou=0.0, min_mask_fraction=0.0, cache_dir=str(cache), rig_framing=framing)
    run_pipeline(data, tmp_path, regime="all", overrides=TRAIN, config=cfg, show_progress=False)
    assert calls and json.loads((tmp_path / "pipeline.json").read_text())["stages"]["nvs"]["references_framed"] == (
        len({view for view, _ in calls}) if framing == "prior" else 0)
    capture = OLATDataset(data)
    center = capture.bounds.center.double()
    radius = silhouette_radius(capture, range(9), center)
    for view, reference_K in calls:
        if framing == "real":
            assert reference_K is None
            continue
        assert torch.allclose(reference_K, framed_intrinsics(
            world_to_camera(center[None], capture.viewmats[view].double())[0], radius, 16, 16), atol=1e-9)
        assert float(reference_K[0, 0]) > 1.3 * float(capture.intrinsics[view, 0, 0])
