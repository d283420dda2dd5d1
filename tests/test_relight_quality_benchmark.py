"""The relighting quality benchmark's bookkeeping (benchmarks/relight_quality.py): means, margins, report,
recorded settings, arguments, the objects it can evaluate."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from repo_scripts import assert_stops_naming, load_script

from diamond_sss.data.analytic import make_capture

relight = load_script("benchmarks/relight_quality.py", "relight_quality_benchmark")


def _image_rows(name: str, light: int, scores: dict[str, tuple[float, float]]) -> list[dict]:
    """The rows of one relit image: ``scores[method] = (psnr, ssim)``."""
    return [{"object": name, "view": 0, "source_light": 0, "light": light, "method": method, "psnr": psnr,
             "ssim": ssim} for method, (psnr, ssim) in scores.items()]


ROWS = [*_image_rows("bunny", 1, {"model": (26.0, 0.8), "source": (22.0, 0.6), "lambertian": (23.0, 0.7),
                                  "hint": (24.0, 0.75)}),
        *_image_rows("blob", 1, {"model": (30.0, 0.9), "source": (20.0, 0.7), "lambertian": (25.0, 0.8),
                                 "hint": (26.0, 0.85)})]


def test_means_per_method_and_object_and_the_models_margin_over_the_two_baselines():
    summary = relight.summarize(ROWS)
    assert summary["images"] == 2 and list(summary["per_object"]) == ["blob", "bunny"]
    assert summary["overall"]["model"] == pytest.approx({"psnr": 28.0, "ssim": 0.85})
    assert summary["overall"]["hint"] == pytest.approx({"psnr": 25.0, "ssim": 0.8})
    assert summary["per_object"]["bunny"]["lambertian"] == {"psnr": 23.0, "ssim": 0.7}
    assert summary["margin_db"] == {"source": 7.0, "lambertian": 4.0} and summary["beats_baselines_by_2db"]
    assert json.loads(json.dumps(summary)) == summary


def test_the_2db_verdict_needs_both_baselines_and_ignores_the_hint():
    rows = [*_image_rows("torus", 1, {"model": (25.0, 0.8), "source": (20.0, 0.6), "lambertian": (24.0, 0.7),
                                      "hint": (30.0, 0.9)}),
            *_image_rows("torus", 2, {"model": (27.0, 0.8), "source": (20.0, 0.6), "lambertian": (25.0, 0.7),
                                      "hint": (30.0, 0.9)})]
    summary = relight.summarize(rows)
    assert summary["images"] == 2 and summary["margin_db"] == pytest.approx({"source": 6.0, "lambertian": 1.5})
    assert not summary["beats_baselines_by_2db"]


def test_the_printed_report_lists_methods_then_objects_then_the_margins():
    lines = relight.report_lines(relight.summarize(ROWS))
    assert lines[:2] == ["method          PSNR    SSIM", "model          28.00   0.850"]
    assert lines[5:9] == ["", "object (PSNR)              model      source  lambertian        hint",
                          "blob                       30.00       20.00       25.00       26.00",
                          "bunny                      26.00       22.00       23.00       24.00"]
    assert lines[-1] == "margin over baselines (dB): {'source': 7.0, 'lambertian': 4.0}; beats both by 2 dB: True"


def test_the_recorded_settings_name_the_shipped_model_when_none_is_given_and_only_the_objects_evaluated():
    args = relight.parse_args(["--data", "heldout/bunny_jade", "heldout/blob_wax", "--samples", "4"])
    settings = relight.run_settings(args, [Path("heldout/blob_wax")])
    assert settings == {"model": "shipped", "steps": 1, "samples": 4, "seed": 0, "objects": ["heldout/blob_wax"]}
    assert json.loads(json.dumps(settings)) == settings
    given = relight.run_settings(relight.parse_args(["--data", "a", "--model", "models/relight"]), [Path("a")])
    assert given["model"] == "models/relight"


@pytest.mark.parametrize("argv, message", [
    (["--samples", "4"], "the following arguments are required: --data"),
    (["--data", "a", "--samples", "many"], "argument --samples: invalid int value: 'many'"),
    (["--data", "a", "--steps", "1.5"], "argument --steps: invalid int value: '1.5'"),
    (["--data", "a", "--sead", "1"], "unrecognized arguments: --sead 1"),
])
def test_a_bad_argument_stops_naming_it(argv, message, capsys):
    assert_stops_naming(relight.parse_args, argv, message, capsys)


def _capture(root: Path, lights: int, maps_views: tuple[int, ...]) -> Path:
    """A 3-view capture under ``lights`` lights with depth / normal maps stored for ``maps_views``."""
    make_capture(root, views=3, lights=lights, size=8)
    transforms = json.loads((root / "transforms_train.json").read_text())
    for view in maps_views:
        for key, channels in (("depth_path", 1), ("normal_path", 3)):
            transforms["frames"][view][key] = f"train/v{view:03d}_{key}.npy"
            np.save(root / transforms["frames"][view][key], np.ones((8, 8, channels), np.float32))
    (root / "transforms_train.json").write_text(json.dumps(transforms))
    return root


def test_objects_without_a_view_to_relight_are_skipped_with_a_warning_naming_them_and_why(tmp_path, capsys):
    usable = _capture(tmp_path / "usable", 2, (1,))
    no_maps = _capture(tmp_path / "no_maps", 2, ())
    one_light = _capture(tmp_path / "one_light", 1, (0, 1, 2))
    assert relight.usable_objects([no_maps, usable, one_light]) == [usable]
    assert capsys.readouterr().err.splitlines() == [
        (f"warning: skipping {no_maps}: no view with images under 2 or more lights has stored depth / normal "
         "maps ('depth_path' / 'normal_path')"),
        f"warning: skipping {one_light}: no view has images under 2 or more lights"]


def test_no_object_with_a_view_to_relight_stops_with_a_message_instead_of_dividing_by_zero(tmp_path, capsys):
    no_maps = _capture(tmp_path / "no_maps", 2, ())
    with pytest.raises(SystemExit) as stop:
        relight.usable_objects([no_maps])
    assert stop.value.code == ("no object to evaluate among the 1 folder(s) of --data: relighting needs a view "
                               "with images under 2 or more lights and stored depth / normal maps")
    assert str(no_maps) in capsys.readouterr().err


def test_a_missing_object_folder_stops_naming_the_option_and_the_folder(tmp_path):
    with pytest.raises(SystemExit, match=f"--data: data folder not found: {tmp_path / 'absent'}"):
        relight.usable_objects([tmp_path / "absent"])
