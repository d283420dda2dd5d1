"""The NVS quality benchmark's bookkeeping (benchmarks/nvs_quality.py): angle bins, table, settings, arguments,
the one-image capture the Gaussian baseline trains on."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from repo_scripts import assert_stops_naming, load_script

from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture

nvs = load_script("benchmarks/nvs_quality.py", "nvs_quality_benchmark")


def _row(method: str, angle: float, psnr: float, ssim: float = 0.5, mask_iou: float = 0.8) -> dict:
    return {"object": "torus", "view": 1, "angle": angle, "method": method, "psnr": psnr, "ssim": ssim,
            "mask_iou": mask_iou}


def test_images_are_averaged_per_half_open_angle_bin_and_method_with_180_degrees_in_the_last_bin():
    rows = [_row("nvs-25-steps", 0.0, 20.0, 0.6, 0.9), _row("gaussians", 10.0, 15.0),
            _row("nvs-25-steps", 29.9, 22.0, 0.8, 0.7), _row("nvs-25-steps", 30.0, 18.0),
            _row("gaussians", 90.0, 12.0), _row("gaussians", 180.0, 10.0)]
    table = nvs.summarise(rows)
    assert [(r["angles"], r["method"], r["images"]) for r in table] == [
        ("0-30", "nvs-25-steps", 2), ("0-30", "gaussians", 1), ("30-60", "nvs-25-steps", 1),
        ("90-180", "gaussians", 2)]
    assert (table[0]["psnr"], table[0]["ssim"], table[0]["mask_iou"]) == pytest.approx((21.0, 0.7, 0.8))
    assert table[-1]["psnr"] == pytest.approx(11.0)


def test_the_markdown_table_has_a_header_and_one_rounded_line_per_summary_row():
    table = nvs.summarise([_row("warp-hint", 45.0, 21.456, 0.81234, 0.98765), _row("warp-hint", 75.0, 9.0)])
    lines = nvs.markdown_table(table).splitlines()
    assert lines[0] == "| angle from reference (deg) | method | images | PSNR | SSIM | mask IoU |"
    assert lines[2:] == ["| 30-60 | warp-hint | 1 | 21.46 | 0.8123 | 0.988 |",
                         "| 60-90 | warp-hint | 1 | 9.00 | 0.5000 | 0.800 |"]
    assert {line.count("|") for line in lines} == {7}


def test_the_recorded_settings_are_the_parsed_command_line_as_json_naming_the_shipped_model_when_none_is_given():
    args = nvs.parse_args(["--data", "heldout/torus", "heldout/bunny", "--steps", "50", "10", "--model", "m"])
    record = nvs.settings_record(args)
    assert json.loads(json.dumps(record)) == record
    assert record["data"] == ["heldout/torus", "heldout/bunny"] and record["model"] == "m"
    assert record["steps"] == [50, 10] and record["out"] == str(nvs.RESULTS)
    assert record["work"] == str(nvs.WORK) and not nvs.WORK.is_relative_to(nvs.RESULTS)  # scratch stays uncommitted
    defaults = nvs.settings_record(nvs.parse_args(["--data", "torus"]))
    assert (defaults["model"], defaults["steps"], defaults["geometry"]) == ("shipped", [25, 1], "maps")


@pytest.mark.parametrize("argv, message", [
    ([], "the following arguments are required: --data"),
    (["--data", "torus", "--steps", "many"], "argument --steps: invalid int value: 'many'"),
    (["--data", "torus", "--guidance", "high"], "argument --guidance: invalid float value: 'high'"),
    (["--data", "torus", "--baseline-iterations", "1.5"], "argument --baseline-iterations: invalid int value"),
])
def test_a_bad_argument_stops_naming_it(argv, message, capsys):
    assert_stops_naming(nvs.parse_args, argv, message, capsys)


def test_the_baseline_capture_holds_only_the_reference_image_under_its_light(tmp_path):
    data = tmp_path / "data"
    make_capture(data, views=3, lights=2, size=8)
    transforms = json.loads((data / "transforms_train.json").read_text())
    for view, frame in enumerate(transforms["frames"]):
        for key, channels in (("depth_path", 1), ("normal_path", 3)):
            frame[key] = f"train/v{view:03d}_{key}.npy"
            np.save(data / frame[key], np.ones((8, 8, channels), np.float32))
    (data / "transforms_train.json").write_text(json.dumps(transforms))
    full = OLATDataset(data)
    single = OLATDataset(nvs.single_image_capture(data, 1, 1, tmp_path / "capture"))
    reference = full.observation_index(1, 1)
    assert (single.num_views, single.num_lights, len(single)) == (1, 1, 1)
    assert single.observations[0].image_path == full.observations[reference].image_path
    torch.testing.assert_close(single.viewmats[0], full.viewmats[1])
    torch.testing.assert_close(single.light_positions[0], full.light_positions[1])
    torch.testing.assert_close(single.load(0).rgb, full.load(reference).rgb)
    assert full.has_geometry_maps(1) and not single.has_geometry_maps(0)


def _without_light_intensities(data: Path) -> None:
    transforms = json.loads((data / "transforms_train.json").read_text())
    for frame in transforms["frames"]:
        del frame["light_intensities"]
    (data / "transforms_train.json").write_text(json.dumps(transforms))


def _with_mask_files(data: Path) -> None:
    """Every image gets a mask file (its alpha, so images and masks agree) listed under ``mask_paths``."""
    from diamond_sss.data.images import load_rgba, write_png

    transforms = json.loads((data / "transforms_train.json").read_text())
    for frame in transforms["frames"]:
        frame["mask_paths"] = [p.replace(".png", "_m.png") for p in frame["file_paths"]]
        for image, mask in zip(frame["file_paths"], frame["mask_paths"]):
            alpha = load_rgba(data / image)[1].numpy()
            write_png(data / mask, (alpha[..., 0] * 255 + 0.5).astype(np.uint8))
    (data / "transforms_train.json").write_text(json.dumps(transforms))


def _with_declared_lattice(data: Path) -> None:
    """Top-level ``cameras`` / ``lights`` (as a generated capture declares them), in reverse order of the frames."""
    transforms = json.loads((data / "transforms_train.json").read_text())
    frames = transforms["frames"]
    transforms["cameras"] = [{"transform_matrix": f["transform_matrix"]} for f in reversed(frames)]
    transforms["lights"] = [{"position": p, "intensity": i} for p, i in
                            zip(frames[0]["light_positions"][::-1], frames[0]["light_intensities"][::-1])]
    (data / "transforms_train.json").write_text(json.dumps(transforms))


@pytest.mark.parametrize("variant, edit", [
    ("sss3dgs", _without_light_intensities),
    ("sss3dgs", _with_mask_files),
    ("sss3dgs", _with_declared_lattice),
    ("per-image", lambda data: None),
], ids=["no-light-intensities", "mask-paths", "declared-lattice", "per-image-frames"])
def test_the_baseline_capture_is_the_reference_image_whatever_the_frame_format(tmp_path, variant, edit):
    data = tmp_path / "data"
    make_capture(data, views=3, lights=2, size=8, variant=variant)
    edit(data)
    full = OLATDataset(data)
    single = OLATDataset(nvs.single_image_capture(data, 2, 1, tmp_path / "capture"))
    reference = full.observations[full.observation_index(2, 1)]
    assert (single.num_views, single.num_lights, len(single)) == (1, 1, 1)
    assert (single.observations[0].image_path, single.observations[0].mask_path) == (
        reference.image_path, reference.mask_path)
    torch.testing.assert_close(single.viewmats[0], full.viewmats[2])
    torch.testing.assert_close(single.intrinsics[0], full.intrinsics[2])
    torch.testing.assert_close(single.light_positions[0], full.light_positions[1])
    torch.testing.assert_close(single.light_intensities[0], full.light_intensities[1])
    torch.testing.assert_close(single.load(0).mask, full.load(full.observation_index(2, 1)).mask)


@pytest.mark.parametrize("option, message", [
    (["--view", "3"], "--view 3 is out of range for {data}: its views are 0..2"),
    (["--view", "-1"], "--view -1 is out of range for {data}: its views are 0..2"),
    (["--light", "2"], "--light 2 is out of range for {data}: its lights are 0..1"),
    (["--view", "0", "--light", "1"], "--view 0 --light 1: {data} has no image of view 0 under light 1"),
], ids=["view-past-the-end", "negative-view", "light-past-the-end", "image-not-captured"])
def test_a_reference_image_outside_a_capture_stops_before_any_work_naming_the_option_and_range(
        tmp_path, option, message):
    good, data = tmp_path / "good", tmp_path / "data"
    make_capture(good, views=3, lights=2, size=8)
    make_capture(data, views=3, lights=2, size=8)
    transforms = json.loads((data / "transforms_train.json").read_text())
    for key in ("file_paths", "light_positions", "light_intensities"):
        del transforms["frames"][0][key][1]
    (data / "transforms_train.json").write_text(json.dumps(transforms))
    args = nvs.parse_args(["--data", str(data), str(good), *option])
    with pytest.raises(SystemExit) as stop:
        nvs.check_reference(args)
    assert str(stop.value.code) == message.format(data=data)
    nvs.check_reference(nvs.parse_args(["--data", str(good), str(data), "--view", "2", "--light", "1"]))


def test_a_missing_or_damaged_capture_stops_naming_the_option_the_file_and_the_key(tmp_path):
    with pytest.raises(SystemExit, match=f"--data: data folder not found: {tmp_path / 'absent'}"):
        nvs.check_reference(nvs.parse_args(["--data", str(tmp_path / "absent")]))
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    (damaged / "transforms_train.json").write_text(json.dumps({"frames": [{"file_paths": []}]}))
    with pytest.raises(SystemExit, match="--data: .*transforms_train.json: frame 0: key 'transform_matrix': missing"):
        nvs.check_reference(nvs.parse_args(["--data", str(damaged)]))


def test_perturbed_depth_moves_the_stored_depth_per_view_and_keys_itself_apart():
    from diamond_sss.data.embedded import embedded_dataset
    from diamond_sss.diffusion.geometry import StoredMapsGeometry

    dataset = OLATDataset(embedded_dataset("finetune/torus_jade"))
    photo = dataset.load(dataset.observation_index(0, 0))
    stored = StoredMapsGeometry().maps(dataset, 0, photo.rgb, photo.mask).depth
    source = nvs.PerturbedDepth(StoredMapsGeometry(), relative=0.1, edge_px=1)
    first = source.maps(dataset, 0, photo.rgb, photo.mask)
    assert torch.equal(first.depth, source.maps(dataset, 0, photo.rgb, photo.mask).depth)  # one draw per view
    assert int((first.depth > 0).sum()) > int((stored > 0).sum())  # the outline dilated by a pixel
    both = (first.depth > 0) & (stored > 0)
    ratio = first.depth[both] / stored[both]
    assert 0.5 < float(ratio.min()) < 1 < float(ratio.max()) < 1.5 and not torch.equal(first.depth, stored)
    assert source.key() == {"kind": "perturbed", "source": {"kind": "maps"}, "relative": 0.1, "edge_px": 1,
                            "seed": 0}


@pytest.mark.parametrize("values", [["nan", "0"], ["-0.1", "0"], ["0.1", "1.5"]])
def test_a_bad_depth_noise_is_refused_naming_the_option(values):
    with pytest.raises(SystemExit):
        nvs.parse_args(["--data", "x", "--depth-noise", *values])
