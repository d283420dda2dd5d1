"""Data layer: conventions round trips, both JSON variants, images, bounds, bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from diamond_sss.data import DataError, OLATDataset
from diamond_sss.data.analytic import FOV_X, SPHERE_RADIUS, make_capture
from diamond_sss.data.conventions import (
    camera_centers,
    intrinsics_from_fov,
    intrinsics_matrix,
    linear_to_srgb,
    look_at_opengl_c2w,
    opencv_w2c_to_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    pixel_grid,
    project_points,
    srgb_to_linear,
    unproject_pixels,
)
from diamond_sss.data.images import load_rgba, reframe, to_srgb8, write_png
from diamond_sss.utils.logs import reset_warnings


def test_intrinsics_from_either_field_of_view():
    square = torch.tensor([[50.0, 0, 50.0], [0, 50.0, 40.0], [0, 0, 1]])
    assert torch.allclose(intrinsics_from_fov(math.radians(90.0), 100, 80), square, atol=1e-4)
    vertical = torch.tensor([[40.0, 0, 50.0], [0, 40.0, 40.0], [0, 0, 1]])
    assert torch.allclose(intrinsics_from_fov(None, 100, 80, math.radians(90.0)), vertical, atol=1e-4)
    both = intrinsics_from_fov(math.radians(90.0), 100, 80, math.radians(90.0))
    assert torch.allclose(both.diagonal(), torch.tensor([50.0, 40.0, 1.0]), atol=1e-4)
    with pytest.raises(ValueError, match="fov_x or fov_y"):
        intrinsics_from_fov(None, 100, 80)


def test_known_point_projects_to_known_pixel():
    c2w = look_at_opengl_c2w(torch.tensor([0.0, 0.0, 3.0]), torch.zeros(3))
    w2c = opengl_c2w_to_opencv_w2c(c2w).float()
    K = intrinsics_from_fov(math.radians(90.0), 100, 80)
    points = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0]])
    uv, z = project_points(points, w2c, K)
    fx = 50.0  # W / (2 tan 45deg)
    assert torch.allclose(z, torch.full((3,), 3.0), atol=1e-5)
    assert torch.allclose(uv[0], torch.tensor([50.0, 40.0]), atol=1e-4)
    assert torch.allclose(uv[1], torch.tensor([50.0 + fx * 0.5 / 3.0, 40.0]), atol=1e-4)
    # world +Y is image-up for this camera: v decreases
    assert torch.allclose(uv[2], torch.tensor([50.0, 40.0 - fx * 0.5 / 3.0]), atol=1e-4)
    back = unproject_pixels(uv, z, w2c, K)
    assert torch.allclose(back, points, atol=1e-5)
    assert torch.allclose(opencv_w2c_to_opengl_c2w(w2c.double()), c2w, atol=1e-6)
    assert torch.allclose(camera_centers(w2c), torch.tensor([0.0, 0.0, 3.0]), atol=1e-5)


def test_srgb_round_trip():
    x = torch.linspace(0, 1, 101)
    assert torch.allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-6)
    assert float(srgb_to_linear(torch.tensor(0.5))) == pytest.approx(0.21404, abs=1e-4)


@pytest.mark.parametrize("variant", ["sss3dgs", "per-image"])
def test_both_variants_load_the_same_lattice(tmp_path, variant):
    truth = make_capture(tmp_path / variant, views=5, lights=3, size=16, variant=variant)
    ds = OLATDataset(tmp_path / variant, "train")
    assert (ds.num_views, ds.num_lights, len(ds)) == (5, 3, 15)
    assert (ds.width, ds.height) == (16, 16)
    assert bool(ds.presence.all())
    assert torch.allclose(ds.intrinsics[0], intrinsics_from_fov(FOV_X, 16, 16))
    for v in range(5):
        expected = opengl_c2w_to_opencv_w2c(torch.from_numpy(truth["c2w"][v])).float()
        assert torch.allclose(ds.viewmats[v], expected, atol=1e-5)
    assert torch.allclose(ds.light_positions.double(), torch.from_numpy(truth["lights"]), atol=1e-5)
    # the object centre projects to the image centre of every view
    uv, _ = project_points(torch.zeros(1, 3), ds.viewmats, ds.intrinsics)
    assert torch.allclose(uv[:, 0], torch.full((5, 2), 8.0), atol=1e-3)
    summary = ds.summary()
    assert summary["views"] == 5 and summary["lights"] == 3 and summary["images"] == 15


@pytest.mark.parametrize("bit_depth,tolerance", [(8, 4e-3), (16, 2e-5)])
def test_images_decode_to_linear_truth(tmp_path, bit_depth, tolerance):
    truth = make_capture(tmp_path, views=2, lights=2, size=16, bit_depth=bit_depth)
    ds = OLATDataset(tmp_path)
    for index, (v, light, _, rgb) in enumerate(truth["images"]):
        sample = ds.load(ds.observation_index(v, light))
        assert sample.rgb.shape == (16, 16, 3) and sample.mask.shape == (16, 16, 1)
        assert float((sample.rgb - torch.from_numpy(rgb).float()).abs().max()) < tolerance
    white = OLATDataset(tmp_path, background="white").load(0)
    outside = white.mask[..., 0] == 0
    assert torch.allclose(white.rgb[outside], torch.ones(3))


def test_downscale_scales_images_and_intrinsics(tmp_path):
    make_capture(tmp_path, views=3, lights=2, size=16)
    full = OLATDataset(tmp_path)
    half = OLATDataset(tmp_path, downscale=2)
    assert (half.width, half.height) == (8, 8)
    assert half.load(0).rgb.shape == (8, 8, 3)
    assert torch.allclose(half.intrinsics[:, :2], full.intrinsics[:, :2] / 2)
    assert torch.allclose(half.load(0).mask.mean(), full.load(0).mask.mean(), atol=1e-6)


def test_scene_bounds_enclose_the_object(tmp_path):
    make_capture(tmp_path, views=8, lights=2, size=16)
    bounds = OLATDataset(tmp_path).bounds
    assert float(bounds.center.norm()) < 1e-3
    assert SPHERE_RADIUS <= bounds.radius < 3.0
    assert bounds.near < 3.0 - SPHERE_RADIUS and bounds.far > 3.0 + SPHERE_RADIUS


def test_lights_within_tolerance_are_one_lattice_light(tmp_path):
    make_capture(tmp_path, views=3, lights=2, size=8)
    path = tmp_path / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta["frames"][1]["light_positions"][0][0] += 1e-6
    path.write_text(json.dumps(meta))
    ds = OLATDataset(tmp_path)
    assert ds.num_lights == 2 and len(ds) == 6


def test_batches_are_seeded_and_cover_each_epoch(tmp_path):
    make_capture(tmp_path, views=3, lights=2, size=8)
    ds = OLATDataset(tmp_path)
    first = [ds.batch_indices(step, 2, seed=7) for step in range(3)]
    assert first == [ds.batch_indices(step, 2, seed=7) for step in range(3)]
    assert sorted(i for batch in first for i in batch) == list(range(6))
    assert first != [ds.batch_indices(step, 2, seed=8) for step in range(3)]
    resumed = ds.iter_batches(2, seed=7, start_step=1)
    assert next(resumed) == first[1]


def test_cache_is_bounded_and_drops_the_least_recently_used(tmp_path):
    make_capture(tmp_path, views=3, lights=2, size=8)
    ds = OLATDataset(tmp_path, cache_images=2)
    expected = OLATDataset(tmp_path, cache_images=0).load(4)
    for i in range(6):
        ds.load(i)
    assert list(ds._cache.entries) == [4, 5]
    ds.load(4)  # a hit makes 4 the most recently used: the next miss drops 5, not 4
    ds.load(0)
    assert list(ds._cache.entries) == [4, 0]
    ds.observations[4].image_path.unlink()  # a hit reads nothing from the disk and serves the decoded image
    hit = ds.load(4)
    assert torch.equal(hit.rgb, expected.rgb) and torch.equal(hit.mask, expected.mask)


def test_loading_writes_nothing_into_the_data_folder(tmp_path):
    make_capture(tmp_path, views=2, lights=2, size=8)
    before = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*")}
    ds = OLATDataset(tmp_path, downscale=2)
    ds.load_batch(range(len(ds)))
    _ = ds.bounds
    after = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*")}
    assert before == after


def test_subset_keeps_lattice_indices(tmp_path):
    make_capture(tmp_path, views=3, lights=2, size=8)
    ds = OLATDataset(tmp_path)
    sub = ds.subset([5, 0])
    assert sub.num_views == 3 and len(sub) == 2
    assert (sub.observations[0].view, sub.observations[0].light) == (ds.observations[5].view,
                                                                     ds.observations[5].light)
    assert int(sub.presence.sum()) == 2 and int(ds.presence.sum()) == 6


# ---------------------------------------------------------------- bad input
def _edit(tmp_path, edit):
    path = tmp_path / "transforms_train.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize(
    "edit,expected",
    [
        (lambda m: m["frames"][1].pop("transform_matrix"), r"frame 1: key 'transform_matrix': missing"),
        (lambda m: m["frames"][0].update(transform_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
         r"frame 0: key 'transform_matrix': expected 4x4"),
        (lambda m: m["frames"][0]["transform_matrix"][0].__setitem__(3, float("nan")),
         r"frame 0: key 'transform_matrix': contains NaN"),
        (lambda m: m["frames"][0].update(transform_matrix=np.zeros((4, 4)).tolist()),
         r"frame 0: key 'transform_matrix': not an invertible"),
        (lambda m: m["frames"][1]["light_positions"].pop(), r"frame 1: key 'light_positions': has 1 entries"),
        (lambda m: m["frames"][0].pop("light_positions"), r"frame 0: key 'light_positions': missing"),
        (lambda m: m["frames"][0]["light_positions"].__setitem__(0, [1, 2]),
         r"frame 0: key 'light_positions\[0\]': expected 3 finite numbers"),
        (lambda m: m.pop("camera_angle_x"), r"frame 0: key 'camera_angle_x': missing"),
        (lambda m: m["frames"][1]["file_paths"].__setitem__(0, "train/nope.png"),
         r"frame 1: key 'file_paths\[0\]': image file not found"),
        (lambda m: m.update(frames={}), r"key 'frames'"),
    ],
)
def test_bad_json_gives_clear_errors(tmp_path, edit, expected):
    make_capture(tmp_path, views=2, lights=2, size=8)
    _edit(tmp_path, edit)
    with pytest.raises(DataError, match=expected) as info:
        OLATDataset(tmp_path)
    assert "transforms_train.json" in str(info.value)


def test_invalid_json_and_missing_split(tmp_path):
    make_capture(tmp_path, views=2, lights=2, size=8)
    with pytest.raises(DataError, match=r"split 'val' not found.*\['train'\]"):
        OLATDataset(tmp_path, "val")
    (tmp_path / "transforms_train.json").write_text("{not json")
    with pytest.raises(DataError, match="invalid JSON"):
        OLATDataset(tmp_path)
    with pytest.raises(DataError, match="data folder not found"):
        OLATDataset(tmp_path / "missing")


def test_images_of_one_view_with_different_sizes(tmp_path):
    make_capture(tmp_path, views=2, lights=2, size=8)
    write_png(tmp_path / "train/v001_l001.png", np.zeros((10, 10, 4), np.uint8))
    with pytest.raises(DataError, match=r"frame 1: key 'w/h': image .*v001_l001.png is 10x10 but view 1 is 8x8"):
        OLATDataset(tmp_path)


def test_rgb_without_alpha_needs_a_mask_file(tmp_path):
    make_capture(tmp_path, views=2, lights=1, size=8)
    write_png(tmp_path / "train/v000_l000.png", np.full((8, 8, 3), 128, np.uint8))
    with pytest.raises(DataError, match=r"frame 0: key 'file_paths\[0\]': .*v000_l000.png has no alpha channel"):
        OLATDataset(tmp_path)
    mask = np.zeros((8, 8), np.uint8)
    mask[2:6, 2:6] = 255
    write_png(tmp_path / "train/v000_l000_mask.png", mask)
    sample = OLATDataset(tmp_path).load(0)
    assert float(sample.mask.sum()) == 16.0
    assert float(sample.rgb[0, 0].abs().sum()) == 0.0  # straight RGB is premultiplied by the mask


@pytest.mark.parametrize("declared, edge", [(True, 1.0), (False, 128 / 255), (None, 128 / 255)])
def test_declared_premultiplied_alpha_decides_for_every_image(tmp_path, declared, edge):
    """An edge pixel of colour 1 and alpha 128/255 in a file whose RGB is not black where alpha is 0 (synth's
    colour and coverage passes differ there): kept as 1 when the capture declares its files premultiplied,
    multiplied by alpha when it declares straight alpha or declares nothing (then each file is guessed)."""
    make_capture(tmp_path, views=2, lights=1, size=8)
    rgba = np.zeros((8, 8, 4), np.uint8)
    rgba[..., :3] = 255
    rgba[0, 0, :3] = 10
    rgba[2:6, 2:6, 3] = 255
    rgba[2, 1, 3] = 128
    write_png(tmp_path / "train/v000_l000.png", rgba)
    if declared is not None:
        path = tmp_path / "transforms_train.json"
        path.write_text(json.dumps({"premultiplied_alpha": declared, **json.loads(path.read_text())}))
    rgb = OLATDataset(tmp_path).load(0).rgb
    assert float(rgb[2, 1, 0]) == pytest.approx(edge, abs=1e-6)
    assert float(rgb[3, 3, 0]) == pytest.approx(1.0)
    assert (float(rgb[0, 0, 0]) > 0) == bool(declared)


def test_written_rgba_holds_no_colour_without_coverage(tmp_path):
    """A premultiplied image with colour where its alpha rounds to 0 in 8 bits (a diffusion model's output): the
    file stores no colour there, so the per-file guess reads it as premultiplied and keeps its edge pixels."""
    rgb = torch.full((2, 2, 3), 0.25)
    alpha = torch.tensor([[0.001, 0.5], [1.0, 0.0]])[..., None]
    written = to_srgb8(rgb, alpha)
    assert written[..., 3].tolist() == [[0, 128], [255, 0]]
    assert written[0, 0, :3].tolist() == [0, 0, 0] and written[1, 1, :3].tolist() == [0, 0, 0]
    assert written[0, 1, :3].tolist() == written[1, 0, :3].tolist() == [137] * 3  # sRGB of 0.25
    loaded, mask = load_rgba(write_png(tmp_path / "image.png", written))
    assert float(loaded[0, 1, 0]) == pytest.approx(0.25, abs=2e-3)  # kept, not multiplied by alpha 128/255
    assert float(mask[0, 1, 0]) == pytest.approx(128 / 255) and float(loaded[0, 0].abs().sum()) == 0.0
    assert to_srgb8(rgb).shape == (2, 2, 3)


def test_premultiplied_alpha_must_be_a_boolean(tmp_path):
    make_capture(tmp_path, views=2, lights=1, size=8)
    path = tmp_path / "transforms_train.json"
    path.write_text(json.dumps({"premultiplied_alpha": "yes", **json.loads(path.read_text())}))
    with pytest.raises(DataError, match=r"transforms_train.json.*'premultiplied_alpha'.*true or false, got 'yes'"):
        OLATDataset(tmp_path)


def test_empty_masks_give_one_warning_line_per_process(tmp_path, caplog):
    make_capture(tmp_path, views=3, lights=1, size=8)
    write_png(tmp_path / "train/v001_l000.png", np.zeros((8, 8, 4), np.uint8))
    write_png(tmp_path / "train/v002_l000.png", np.zeros((8, 8, 4), np.uint8))
    reset_warnings()
    for _ in range(2):
        ds = OLATDataset(tmp_path)
        for view in (0, 1, 2):
            ds.load(ds.observation_index(view, 0))
    messages = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(messages) == 1 and "v001_l000.png: the mask is empty (frame 1 of" in messages[0]


def test_declared_lattice_keeps_cameras_and_lights_without_images(tmp_path):
    truth = make_capture(tmp_path, views=4, lights=3, size=8)
    full = OLATDataset(tmp_path)
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    cameras = [{"transform_matrix": c2w.tolist()} for c2w in truth["c2w"]]
    lights = [{"position": p.tolist(), "intensity": [1.0, 1.0, 1.0]} for p in truth["lights"]]
    frame = meta["frames"][2]
    sparse = {"camera_angle_x": meta["camera_angle_x"], "cameras": cameras, "lights": lights,
              "frames": [{**frame, "file_paths": frame["file_paths"][2:], "light_positions": frame["light_positions"][2:],
                          "light_intensities": frame["light_intensities"][2:]}]}
    (tmp_path / "transforms_sparse.json").write_text(json.dumps(sparse))
    ds = OLATDataset(tmp_path, "sparse")
    assert (ds.num_views, ds.num_lights, len(ds)) == (4, 3, 1)
    assert (ds.observations[0].view, ds.observations[0].light) == (2, 2)
    assert torch.allclose(ds.viewmats, full.viewmats) and torch.allclose(ds.light_positions, full.light_positions)
    assert ds.cameras[0].frame == -1 and (ds.cameras[0].width, ds.cameras[0].height) == (8, 8)
    sparse["lights"][1] = {"intensity": [1, 1, 1]}
    (tmp_path / "transforms_sparse.json").write_text(json.dumps(sparse))
    with pytest.raises(DataError, match=r"key 'lights': lights\[1\]: expected an object with 'position'"):
        OLATDataset(tmp_path, "sparse")


@pytest.mark.parametrize("split", ["train", "test"])
def test_loader_matches_the_synthetic_meta_json(split):
    from diamond_sss.data.embedded import embedded_dataset

    root = embedded_dataset()
    meta = json.loads((root / "meta.json").read_text())
    ds = OLATDataset(root, split)
    c2w = torch.tensor(meta["cameras"][split], dtype=torch.float64)
    lights = torch.tensor(meta["lights"][split], dtype=torch.float32)
    assert (ds.num_views, ds.num_lights) == (len(c2w), len(lights))
    assert len(ds) == len(meta["pairs"][split]) == ds.num_views * ds.num_lights
    assert torch.allclose(ds.viewmats.double(), opengl_c2w_to_opencv_w2c(c2w), atol=1e-5)
    assert torch.allclose(ds.light_positions, lights, atol=1e-5)
    assert (ds.width, ds.height) == tuple(meta["size"])
    assert torch.allclose(ds.intrinsics[0], intrinsics_from_fov(meta["camera_angle_x"], *meta["size"]), atol=1e-4)
    # the object (unit sphere at the origin) projects to the image centre of every view
    uv, z = project_points(torch.zeros(1, 3), ds.viewmats, ds.intrinsics)
    assert torch.allclose(uv[:, 0], torch.full((ds.num_views, 2), 32.0), atol=0.5)
    assert bool((z > 1.0).all())
    # and fills a sane part of it: in the sphere's bounds, masks neither empty nor full
    sample = ds.load(0)
    assert 0.02 < float(sample.mask.mean()) < 0.6
    assert ds.bounds.radius >= 1.0 and ds.bounds.near < meta["stage"]["camera_radius"] - 1.0


def test_corrupt_and_truncated_images_name_the_file(tmp_path):
    make_capture(tmp_path, views=2, lights=2, size=8)
    (tmp_path / "train/v000_l001.png").write_text("not an image")
    with pytest.raises(DataError, match=r"v000_l001.png: not a readable image"):
        OLATDataset(tmp_path)
    make_capture(tmp_path, views=2, lights=2, size=8)
    path = tmp_path / "train/v001_l000.png"
    path.write_bytes(path.read_bytes()[:60])
    ds = OLATDataset(tmp_path)  # the header is intact: the error comes when the pixels are read
    with pytest.raises(DataError, match=r"v001_l000.png: cannot decode image, corrupt or truncated"):
        ds.load(ds.observation_index(1, 0))


def test_sample_bilinear_hits_pixel_centres():
    from diamond_sss.data.conventions import sample_bilinear

    image = torch.arange(12, dtype=torch.float32).reshape(1, 3, 4)
    uv = torch.tensor([[[0.5, 0.5], [3.5, 2.5], [1.0, 0.5], [2.5, 1.0], [-5.0, 0.5]]])
    assert torch.allclose(sample_bilinear(image, uv), torch.tensor([[0.0, 11.0, 0.5, 4.0, 0.0]]), atol=1e-5)


def test_reframe_reads_each_pixel_through_the_other_intrinsics():
    """A ramp ``I(u, v) = u + 10 v`` (bilinear reads it exactly): the same intrinsics give the image back; a focal
    length doubled about another principal point gives ``I(K_from K_to^-1 p')``; pixels that read outside are 0."""
    height, width = 12, 16
    grid = pixel_grid(height, width)
    ramp = (grid[..., 0] + 10.0 * grid[..., 1])[None, None]
    K_from = intrinsics_matrix(20.0, 20.0, 8.0, 6.0)[None]
    assert torch.allclose(reframe(ramp, K_from, K_from), ramp, atol=1e-4)
    K_to = intrinsics_matrix(40.0, 40.0, 7.0, 5.0)[None]
    out = reframe(ramp, K_from, K_to)[0, 0]
    u = (grid[..., 0] - 7.0) / 2.0 + 8.0  # p = K_from K_to^-1 p'
    v = (grid[..., 1] - 5.0) / 2.0 + 6.0
    inside = (u >= 0.5) & (u <= width - 0.5) & (v >= 0.5) & (v <= height - 0.5)
    assert inside.float().mean() > 0.5
    assert torch.allclose(out[inside], (u + 10.0 * v)[inside], atol=1e-3)
    zoomed_out = reframe(ramp, K_from, intrinsics_matrix(5.0, 5.0, 8.0, 6.0)[None])[0, 0]
    assert zoomed_out[0, 0] == 0.0 and zoomed_out[6, 8] > 0.0  # the corner reads far outside, the centre inside
    depth = torch.zeros(1, 1, height, width)
    depth[..., 4:8, 6:10] = 3.0
    assert set(reframe(depth, K_from, K_to, mode="nearest").unique().tolist()) <= {0.0, 3.0}  # no blend with 0
    with pytest.raises(ValueError, match=r"K_from / K_to \[N,3,3\]"):
        reframe(ramp, K_from[0], K_to)
    for bad in (intrinsics_matrix(0.0, 40.0, 7.0, 5.0)[None], torch.full((1, 3, 3), float("nan"))):
        with pytest.raises(ValueError, match="finite with positive focal lengths"):
            reframe(ramp, K_from, bad)


def test_reframe_zooming_out_averages_like_an_area_resize():
    """Half the focal length about the image centre: the centre half of the result is the image area-resized to half
    its size (a box filter, no aliasing of a checkerboard into stripes)."""
    size = 16
    checker = ((torch.arange(size)[:, None] + torch.arange(size)[None, :]) % 2).float()[None, None]
    K_from = intrinsics_matrix(20.0, 20.0, 8.0, 8.0)[None]
    out = reframe(checker, K_from, intrinsics_matrix(10.0, 10.0, 8.0, 8.0)[None])[0, 0]
    assert torch.allclose(out[4:12, 4:12], torch.full((8, 8), 0.5), atol=1e-6)
    assert out[:4].abs().max() == 0.0
    assert torch.allclose(reframe(checker, K_from, K_from), checker, atol=1e-6)  # no zoom: no averaging
