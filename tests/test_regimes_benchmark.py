"""The sparse-regime benchmark's bookkeeping (benchmarks/regimes.py): names, labels, targets, collected runs."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest
from repo_scripts import load_script

from diamond_sss.data.analytic import make_capture, make_capture_with_test_split
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.errors import DataError
from diamond_sss.data.images import write_png
from diamond_sss.diffusion.common.manifest import GeneratedImage, image_paths, write_image_manifest

regimes = load_script("benchmarks/regimes.py", "regimes_benchmark")


def test_variant_names_and_labels():
    assert regimes.share_value("auto") is None and regimes.share_value("0.7") == 0.7
    assert regimes.variant_name("full") == "full" and regimes.variant_name("sss3dgs", 0.3) == "sss3dgs"
    name = regimes.variant_name("full", 0.3, 1.0, "batch2")
    assert name == "full_share30_agree1_batch2"
    assert regimes.variant_label(name) == ("+ novel views (full pipeline) "
                                           "[min_real_share 0.3, agreement_power 1, batch2]")
    assert regimes.variant_label(regimes.variant_name("+relight", None, 0.0)) == "+ relighting"


def test_pipeline_settings_take_the_fields_types():
    assert regimes.pipeline_setting("rounds", "int", "2") == 2
    assert regimes.pipeline_setting("min_real_share", "float | None", "0.7") == 0.7
    assert regimes.pipeline_setting("min_real_share", "float | None", "None") is None
    assert regimes.pipeline_setting("nvs_model", "str | None", "models/nvs") == "models/nvs"
    assert regimes.pipeline_setting("augment", "tuple[str, ...]", "nvs") == ("nvs",)
    assert regimes.pipeline_setting("augment", "tuple[str, ...]", "nvs,relight") == ("nvs", "relight")
    with pytest.raises(SystemExit, match="--pipeline-set rounds=many: rounds takes int"):
        regimes.pipeline_setting("rounds", "int", "many")
    assert regimes.pipeline_setting("nvs_canonical", "bool", "True") is True
    assert regimes.pipeline_setting("nvs_canonical", "bool", "false") is False
    with pytest.raises(SystemExit, match="nvs_canonical takes true or false"):
        regimes.pipeline_setting("nvs_canonical", "bool", "1")


def _row(name: str, regime: str, method: str, psnr: float, iou: float, form: str = "lattice") -> dict:
    return {"object": name, "form": form, "regime": regime, "method": method, "psnr": psnr, "ssim": 0.5,
            "mask_iou": iou, "real_images": 9, "synthetic_images": 0}


def test_targets_are_judged_per_object_and_for_the_mean():
    rows = [_row("a", regimes.NINE, "sss3dgs", 15.0, 0.80), _row("a", regimes.NINE, "full", 17.5, 0.85),
            _row("b", regimes.NINE, "sss3dgs", 15.0, 0.80), _row("b", regimes.NINE, "full", 16.5, 0.90),
            _row("a", regimes.THIRTY, "full", 24.0, 0.9), _row("a", regimes.THIRTY, "sss3dgs", 23.5, 0.9),
            _row("a", "all", "dense", 25.5, 0.95),
            _row("a", "images=9", "sss3dgs", 14.0, 0.80, "sparse"), _row("a", "images=9", "full", 14.5, 0.79, "sparse")]
    lines = regimes.target_lines([*rows, *regimes.mean_rows(rows)])
    nine, thirty = "lattice `views=3,lights=3`", "lattice `views=5,lights=6`"
    assert f"- a, {nine}: full - sss3dgs = +2.50 dB, mask IoU +0.050 (target >= +2 dB and > 0: met)" in lines
    assert f"- b, {nine}: full - sss3dgs = +1.50 dB, mask IoU +0.100 (target >= +2 dB and > 0: not met)" in lines
    assert f"- mean (2), {nine}: full - sss3dgs = +2.00 dB, mask IoU +0.075 (target >= +2 dB and > 0: met)" in lines
    assert f"- a, {thirty}: full - dense = -1.50 dB (target >= -2 dB: met)" in lines
    assert f"- a, {thirty}: full - sss3dgs = +0.50 dB (target >= +1 dB: not met)" in lines
    assert ("- a, sparse `images=9`: full - sss3dgs = +0.50 dB, mask IoU -0.010 (target >= +2 dB and > 0: not met)"
            in lines)
    table = regimes.markdown(rows, 1000, "test machine")
    assert ("| a | lattice | `views=3,lights=3` | + novel views (full pipeline) | 17.50 | 0.5000 | 0.850 | 9 / 0 |  |"
            in table)
    assert "n / (n + 9) of the images drawn" in table and table.splitlines()[0].endswith("test machine")


def test_noise_ceilings_are_listed_for_rendered_captures_with_the_dense_rows_distance():
    rows = [_row("a", regimes.THIRTY, "full", 24.0, 0.9), _row("a", "all", "dense", 25.5, 0.95),
            _row("b", regimes.THIRTY, "full", 20.0, 0.9)]
    table = regimes.markdown(rows, 1000, "", {"a": 27.5, "b": 26.0, "c": None})
    assert table.endswith("- a: 27.50 dB (dense row 2.00 dB under it)\n- b: 26.00 dB\n")
    assert "Noise ceilings" not in regimes.markdown(rows, 1000, "")


def test_the_noise_ceiling_renders_a_second_test_split_once_and_only_for_a_synth_capture(tmp_path, monkeypatch):
    from diamond_sss.data.dataset import OLATDataset

    data, references = tmp_path / "capture", tmp_path / "references"
    make_capture(data, views=2, lights=2, size=16, split="test")
    assert regimes.noise_ceiling_of(data, references) is None  # no meta.json: nothing to render again
    (data / "meta.json").write_text("{}")
    with pytest.raises(SystemExit, match=r"--noise-ceilings: .*meta.json: not a `diamond-sss synth` meta file"):
        regimes.noise_ceiling_of(data, references)  # the benchmark stops, naming the file, before any render
    assert not references.exists()
    rendered = []

    def render(out):  # stands in for Mitsuba: the same test views under slightly moved lights
        rendered.append(out)
        make_capture(out, views=2, lights=2, size=16, split="test", light_offset=0.05)

    monkeypatch.setattr(regimes, "noise_reference_config", lambda capture, out: out if capture == data else None)
    monkeypatch.setattr(regimes, "synthesize", render)
    first = regimes.noise_ceiling_of(data, references)
    second = regimes.noise_ceiling_of(data, references)
    assert rendered == [references / "capture"]  # rendered once, then reused
    expected = regimes.noise_ceiling(OLATDataset(data, "test"), OLATDataset(references / "capture", "test"))
    assert first == second == pytest.approx(expected["render_psnr"] + 10 * math.log10(2.0))
    assert 10.0 < first < 80.0


def test_recorded_reads_a_finished_pipeline_and_skips_an_unfinished_one(tmp_path):
    run = tmp_path / "full"
    run.mkdir()
    assert regimes.recorded(run) is None
    stages = {"final": {"real_images": 30, "synthetic_images": 208, "real_share": 0.1261, "seconds": 1.0}}
    (run / "pipeline.json").write_text(json.dumps({"stages": stages}))
    assert regimes.recorded(run) is None  # not evaluated yet
    stages["eval"] = {"psnr": 20.5, "ssim": 0.7, "mask_iou": 0.93}
    (run / "pipeline.json").write_text(json.dumps({"stages": stages}))
    final, metrics = regimes.recorded(run)
    assert final == run / "final" and metrics == {"psnr": 20.5, "ssim": 0.7, "mask_iou": 0.93, "real_images": 30,
                                                  "synthetic_images": 208, "real_share": 0.1261}


def test_a_rows_minutes_are_what_its_run_recorded_not_the_time_to_collect_it(tmp_path):
    training, pipeline = tmp_path / "sss3dgs", tmp_path / "full"
    training.mkdir()
    pipeline.mkdir()
    assert regimes.run_minutes(training) is None
    (training / "train_summary.json").write_text(json.dumps({"steps": 1000, "seconds": 273.6}))
    stages = {"prelim": {"seconds": 0.0, "reused": str(training)}, "nvs": {"seconds": 4.8},
              "final": {"seconds": 113.2, "real_images": 30}, "eval": {"seconds": 3.0, "psnr": 26.3}}
    (pipeline / "pipeline.json").write_text(json.dumps({"stages": stages}))
    assert regimes.run_minutes(training) == pytest.approx(273.6 / 60)
    assert regimes.run_minutes(pipeline) == pytest.approx(121.0 / 60)
    (training / "train_summary.json").write_text("{not json")
    with pytest.raises(DataError, match="train_summary.json: damaged or invalid JSON"):
        regimes.run_minutes(training)


def test_a_bad_pipeline_setting_stops_before_any_training(tmp_path):
    with pytest.raises(ValueError, match=r"unknown stage\(s\) \['nvx'\]"):
        regimes.run_method("full", tmp_path / "capture", tmp_path / "runs", "views=2,lights=1", 10,
                           pipeline_set={"augment": "nvx"}, tag="bad")
    assert not (tmp_path / "runs").exists()


def test_pipeline_settings_need_a_tag(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["regimes.py", "--pipeline-set", "nvs_views=0"])
    with pytest.raises(SystemExit):
        regimes.main()
    assert "--pipeline-set and --tag go together" in capsys.readouterr().err


def test_a_finished_run_is_reused_only_with_the_same_settings(tmp_path, monkeypatch):
    data = tmp_path / "capture"
    make_capture_with_test_split(data, views=6, lights=3, size=16)
    runs = tmp_path / "runs"
    monkeypatch.setattr(regimes, "short_schedule", lambda iterations, **_: {"iterations": iterations,
                                                                               "num_gaussians": 200})
    run, first = regimes.run_method("sss3dgs", data, runs, "views=2,lights=1", 2)
    written = (run / "model.safetensors").stat().st_mtime_ns
    _, again = regimes.run_method("sss3dgs", data, runs, "views=2,lights=1", 2)
    assert (run / "model.safetensors").stat().st_mtime_ns == written and again == first  # reused as it was
    monkeypatch.setattr(regimes, "short_schedule", lambda iterations, **_: {"iterations": iterations,
                                                                               "num_gaussians": 250})
    regimes.run_method("sss3dgs", data, runs, "views=2,lights=1", 2)  # other settings: trained again
    aside = [path for path in runs.iterdir() if path.name.startswith("sss3dgs.")]
    assert len(aside) == 1 and (aside[0] / "model.safetensors").is_file()
    assert json.loads((run / "train_summary.json").read_text())["num_gaussians"] == 250


def test_the_grid_has_a_row_per_object_with_each_runs_render_and_psnr(tmp_path, monkeypatch):
    import imageio.v3 as iio

    objects = []
    for name, offset in (("first", 0.0), ("second", 0.3)):
        data = tmp_path / name
        make_capture_with_test_split(data, views=6, lights=3, size=16, camera_offset=offset)
        objects.append(data)
    monkeypatch.setattr(regimes, "short_schedule", lambda iterations, **_: {"iterations": iterations,
                                                                               "num_gaussians": 200})
    finals, rows = {}, []
    for data in objects:
        run, metrics = regimes.run_method("sss3dgs", data, tmp_path / "runs" / data.name, regimes.NINE, 2)
        rows.append({"object": data.name, "regime": regimes.NINE, "method": "sss3dgs", "psnr": metrics["psnr"]})
        finals[regimes.grid_key(rows[-1])] = run
    rows.append({**rows[-1], "form": "sparse", "psnr": 1.0})  # the same run as the sparse form's row: its own cell
    finals[regimes.grid_key(rows[-1])] = run
    drawn = {}
    real = regimes.save_image_grid
    monkeypatch.setattr(regimes, "save_image_grid", lambda path, grid, **labels: drawn.update(grid=grid, **labels)
                        or real(path, grid, **labels))
    path = regimes.save_regimes_grid(tmp_path / "grid.png", objects, finals, rows)
    assert drawn["row_labels"] == ["first", "second"]
    assert [len(row) for row in drawn["grid"]] == [2, 3]
    assert drawn["cell_labels"][1] == ["ground truth", f"9: sss3dgs {rows[1]['psnr']:.2f}",
                                       "9 sparse: sss3dgs 1.00"]
    assert iio.imread(path).shape[0] > iio.imread(path).shape[1] / 3  # two rows of up to three cells


def test_a_pipeline_rows_final_reconstruction_trains_on_the_rmse_and_its_baseline_on_l1(tmp_path, monkeypatch):
    from diamond_sss.training.overrides import make_config

    class Handed(Exception):
        """Raised by the pipeline's stand-in once the final reconstruction's settings were handed over."""

    handed = {}

    def pipeline(data, folder, **kwargs):
        handed.update(kwargs["overrides"])
        raise Handed

    monkeypatch.setattr(regimes, "run_pipeline", pipeline)
    runs = tmp_path / "runs"
    (runs / "sss3dgs").mkdir(parents=True)
    (runs / "sss3dgs" / "model.safetensors").touch()  # a finished preliminary run: nothing trained here
    with pytest.raises(Handed):
        regimes.run_method("full", tmp_path / "capture", runs, regimes.NINE, 1000)
    assert make_config("diamond", overrides=handed).losses.photometric_error == "rmse"
    baseline = make_config("sss3dgs", overrides=regimes.short_schedule(1000))
    assert baseline.losses.photometric_error == "l1"


def test_the_sparse_form_is_the_regimes_images_as_a_capture_of_their_own_written_once(tmp_path):
    data = tmp_path / "obj"
    make_capture_with_test_split(data, views=6, lights=3, size=16)
    folder = regimes.sparse_capture(data, tmp_path / "runs", "views=2,lights=1", seed=0)
    assert folder == tmp_path / "runs" / "captures" / "obj_views2_lights1"
    sparse = OLATDataset(folder)
    assert (len(sparse), sparse.num_views, sparse.num_lights) == (2, 2, 1)
    assert len(OLATDataset(folder, "test")) == 4
    written = (folder / "transforms_train.json").stat().st_mtime_ns
    assert regimes.sparse_capture(data, tmp_path / "runs", "views=2,lights=1", seed=0) == folder
    assert (folder / "transforms_train.json").stat().st_mtime_ns == written


def test_stage_seconds_of_a_pipeline_folder(tmp_path):
    (tmp_path / "pipeline.json").write_text(json.dumps({"stages": {"prelim": {"seconds": 0.0, "reused": "x"},
                                                                    "nvs": {"seconds": 12.5, "targets": 3}}}))
    assert regimes.stage_seconds(tmp_path) == {"prelim": 0.0, "nvs": 12.5}
    (tmp_path / "round1").mkdir()  # an earlier round's stages count too
    (tmp_path / "round1" / "pipeline.json").write_text(json.dumps({"stages": {"prelim": {"seconds": 30.0},
                                                                               "nvs": {"seconds": 10.0}}}))
    assert regimes.stage_seconds(tmp_path) == {"prelim": 30.0, "nvs": 22.5}
    assert regimes.run_minutes(tmp_path) == pytest.approx(52.5 / 60)
    assert regimes.stage_seconds(tmp_path / "a_training_run") == {}


def test_round_metrics_of_a_pipeline_folder_in_round_order(tmp_path):
    def evaluated(final, psnr, iou):
        (final / "eval_test").mkdir(parents=True)
        (final / "eval_test" / "metrics.json").write_text(json.dumps({"psnr": psnr, "mask_iou": iou, "ssim": 0.5}))

    for k, psnr in ((1, 20.0), (2, 21.0), (10, 23.0)):
        evaluated(tmp_path / f"round{k}" / "final", psnr, 0.9)
    (tmp_path / "round3" / "final").mkdir(parents=True)  # not evaluated yet: left out
    evaluated(tmp_path / "final", 24.5, 0.95)
    (tmp_path / "round2" / "pipeline.json").write_text(json.dumps(
        {"stages": {"repair": {"mask_area_vs_previous_round": 0.956}, "final": {"real_images": 9}}}))
    (tmp_path / "pipeline.json").write_text(json.dumps(
        {"stages": {"repair": {"mask_area_vs_previous_round": 0.91}, "final": {"kept": "round10/final"}}}))
    for folder, pixels in ((tmp_path / "round3", 8), (tmp_path / "round10", 6)):  # no ratio recorded: computed
        mask = np.zeros((4, 4), dtype=np.uint8)
        mask.flat[:pixels] = 255
        image, mask_path = image_paths(folder / "repair", "v0_l1")
        write_png(image, np.zeros((4, 4, 3), dtype=np.uint8))
        write_png(mask_path, mask)
        write_image_manifest(folder / "repair", [GeneratedImage(0, 1, image, mask_path)])
    rounds = regimes.round_metrics(tmp_path)
    assert [item["psnr"] for item in rounds] == [20.0, 21.0, 23.0, 24.5]
    assert [item["round"] for item in rounds] == [1, 2, 10, 11] and rounds[-1]["mask_iou"] == 0.95
    assert [item["mask_area"] for item in rounds] == [None, 0.956, 0.75, 0.91]  # round 10 against round 3
    assert [item["kept"] for item in rounds] == [False, False, False, True]
    single = tmp_path / "single"
    evaluated(single / "final", 22.0, 0.9)
    assert regimes.round_metrics(single) == [] and regimes.round_metrics(tmp_path / "absent") == []
    rows = [{"object": "blob", "form": "sparse", "regime": "images=9", "method": "repair", "rounds": rounds[:2]},
            {"object": "blob", "form": "sparse", "regime": "images=9", "method": "sss3dgs", "rounds": []}]
    rows.insert(1, {**rows[0], "method": "repair seed 1", "rounds": rounds[2:]})
    assert regimes.rounds_lines(rows) == [
        "- blob, sparse `images=9`, repair: 20.00 (0.900) -> [masks 95.6%] 21.00 (0.900)",
        "- blob, sparse `images=9`, repair seed 1: [masks 75.0%] 23.00 (0.900) -> [masks 91.0%] 24.50 (0.950) kept"]
    (tmp_path / "round1" / "final" / "eval_test" / "metrics.json").write_text(json.dumps({"ssim": 0.5}))
    with pytest.raises(ValueError, match=r"round1/final/eval_test/metrics.json: no psnr or mask_iou"):
        regimes.round_metrics(tmp_path)
