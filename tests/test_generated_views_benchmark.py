"""The generated-images benchmark (benchmarks/generated_views.py): each generated image scored against the truth and
beside the preliminary reconstruction's render."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from repo_scripts import load_script

from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture
from diamond_sss.data.images import write_png
from diamond_sss.diffusion.common.manifest import GeneratedImage, write_image_manifest
from diamond_sss.training.run import train_from_preset

generated_views = load_script("benchmarks/generated_views.py", "generated_views_benchmark")

TINY = {"iterations": 2, "num_gaussians": 200, "batch_size": 1, "lambda_lpips": 0.0, "raytrace_gaussians": 32,
        "mv_pixels_per_pair": 16, "mv_pairs_per_step": 1, "densify": False, "image_log_every": 1000, "device": "cpu"}


def _copy_of_truth(dataset: OLATDataset, view: int, light: int, folder) -> GeneratedImage:
    obs = dataset.observations[dataset.observation_index(view, light)]
    folder.mkdir(parents=True, exist_ok=True)
    image, mask = folder / f"view_{view:03d}.png", folder / f"view_{view:03d}_mask.png"
    shutil.copyfile(obs.image_path, image)
    alpha = dataset.load(dataset.observation_index(view, light)).mask[..., 0].numpy()
    write_png(mask, (alpha * 255 + 0.5).astype(np.uint8))
    return GeneratedImage(view, light, image, mask)


def _black(view: int, light: int, size: int, folder) -> GeneratedImage:
    image, mask = folder / f"view_{view:03d}.png", folder / f"view_{view:03d}_mask.png"
    write_png(image, np.zeros((size, size, 3), dtype=np.uint8))
    write_png(mask, np.zeros((size, size), dtype=np.uint8))
    return GeneratedImage(view, light, image, mask)


@pytest.fixture(scope="module")
def pipeline_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("generated")
    data = root / "capture"
    make_capture(data, views=6, lights=3, size=16)
    train_from_preset(data, root / "prelim", overrides=TINY, show_progress=False)
    run = root / "run"
    dataset = OLATDataset(data, "train")
    nvs = run / "nvs" / "l000_v000"
    write_image_manifest(nvs, [_copy_of_truth(dataset, 1, 0, nvs), _black(2, 0, 16, nvs)])
    relit = run / "relight" / "out"
    write_image_manifest(relit, [_copy_of_truth(dataset, 3, 1, relit)])
    (run / "pipeline.json").write_text(json.dumps({"inputs": {"data": str(data)},
                                                   "stages": {"prelim": {"reused": str(root / "prelim")}}}))
    return run


def test_each_generated_image_is_scored_against_its_truth_beside_the_preliminary_render(pipeline_run):
    rows, grid = generated_views.score_run(pipeline_run)
    by_view = {(r["stage"], r["view"], r["light"]): r for r in rows}
    assert set(by_view) == {("nvs", 1, 0), ("nvs", 2, 0), ("relight", 3, 1)}
    copy, black = by_view["nvs", 1, 0], by_view["nvs", 2, 0]
    assert copy["generated_psnr"] == 100.0 and copy["generated_mask_iou"] == pytest.approx(1.0)
    assert black["generated_mask_iou"] == 0.0 and black["generated_psnr"] < copy["generated_psnr"]
    assert copy["prelim_psnr"] < 100.0  # two training steps do not reproduce the truth
    assert len(grid) == 2 and all(len(row) == 3 for row in grid)  # the nvs images: truth | generated | prelim
    table = generated_views.summarise(rows)
    nvs, relight = (next(r for r in table if r["stage"] == stage) for stage in ("nvs", "relight"))
    assert nvs["images"] == 2 and relight["images"] == 1 and relight["wins"] == 1.0
    assert nvs["wins"] == (0.5 if black["generated_psnr"] <= black["prelim_psnr"] else 1.0)
    assert nvs["generated_psnr"] == pytest.approx((copy["generated_psnr"] + black["generated_psnr"]) / 2)
    assert f"| {pipeline_run} | relight | 1 | 100.00 / 1.000 / 1.000 |" in generated_views.markdown(table)


def test_a_folder_that_is_not_a_pipeline_run_is_named(tmp_path, pipeline_run):
    with pytest.raises(SystemExit, match=f"{tmp_path} holds no pipeline.json"):
        generated_views.run_inputs(tmp_path)
    record = json.loads((pipeline_run / "pipeline.json").read_text())
    record["stages"]["prelim"]["reused"] = str(tmp_path / "gone")
    (tmp_path / "pipeline.json").write_text(json.dumps(record))
    with pytest.raises(SystemExit, match="its preliminary reconstruction .*gone is gone"):
        generated_views.run_inputs(tmp_path)
    (tmp_path / "pipeline.json").write_text("{not json")
    with pytest.raises(SystemExit, match="pipeline.json: not valid JSON"):
        generated_views.run_inputs(tmp_path)
    (tmp_path / "pipeline.json").write_text(json.dumps({"stages": {}}))
    with pytest.raises(SystemExit, match=r"pipeline.json: no inputs.data \(the capture folder\)"):
        generated_views.run_inputs(tmp_path)


def test_a_generated_image_of_the_wrong_size_is_named(tmp_path, pipeline_run):
    run = tmp_path / "run"
    shutil.copytree(pipeline_run, run)
    item = _black(4, 0, 8, run / "nvs" / "l000_v000")
    write_image_manifest(run / "nvs" / "l000_v000", [item])
    with pytest.raises(ValueError, match="view_004.png: generated image is 8x8, the lattice's view 4 is 16x16"):
        generated_views.score_run(run)
