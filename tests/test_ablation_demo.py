"""The demo command and the multi-view ablation run end to end on a tiny analytic capture."""

from __future__ import annotations

import json
import re

import pytest
import torch
from safetensors.torch import load_file

from diamond_sss.cli.main import main
from diamond_sss.data.analytic import make_capture_with_test_split
from diamond_sss.experiments.ablation import regime_slug, run_ablation


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return make_capture_with_test_split(tmp_path_factory.mktemp("capture"), views=6, lights=3, size=16)


def test_regime_slug():
    assert regime_slug("views=5%,lights=5%") == "views5p_lights5p"
    assert regime_slug("all") == "all"


def test_ablation_writes_table_json_and_grid(capture, tmp_path):
    rows = run_ablation(capture, tmp_path, variants=["diamond-no-mv", "+both"], regimes=["views=50%,lights=all"],
                        iterations=2, overrides={"num_gaussians": 200, "lambda_lpips": 0.0, "log_every": 1},
                        show_progress=False)
    assert [(r.variant, r.regime) for r in rows] == [("diamond-no-mv", "views=50%,lights=all"),
                                                      ("+both", "views=50%,lights=all")]
    saved = json.loads((tmp_path / "ablation.json").read_text())
    assert len(saved) == 2 and all("psnr" in row and "mask_iou" in row for row in saved)
    config = json.loads((tmp_path / "views50p_lightsall" / "diamond-no-mv" / "config.json").read_text())
    assert config["losses"]["lambda_sil"] == 0.0 and config["losses"]["lambda_depth"] == 0.0
    assert (tmp_path / "ablation_grid.png").is_file()
    assert "| `views=50%,lights=all` | +both |" in (tmp_path / "ablation.md").read_text()
    with pytest.raises(ValueError, match="unknown ablation variants"):
        run_ablation(capture, tmp_path, variants=["+normals"])


def test_ablation_gives_the_dense_regime_its_own_overrides(capture, tmp_path, monkeypatch):
    """Dense by the images a regime selects (here 18 and 9), not by its name: with dense from 10 images `all` takes
    the dense overrides, from 19 neither regime does."""
    from diamond_sss.experiments import ablation

    for threshold, expected in ((10, {"all": 2, "views50p_lightsall": 1}), (19, {"all": 1, "views50p_lightsall": 1})):
        monkeypatch.setattr(ablation, "DENSE_MIN_IMAGES", threshold)
        out = tmp_path / str(threshold)
        run_ablation(capture, out, variants=["sss3dgs"], regimes=["all", "views=50%,lights=all"], iterations=1,
                     overrides={"num_gaussians": 200, "lambda_lpips": 0.0, "batch_size": 1},
                     dense_overrides={"batch_size": 2}, show_progress=False)
        batch = {slug: json.loads((out / slug / "sss3dgs" / "config.json").read_text())["schedule"]["batch_size"]
                 for slug in expected}
        assert batch == expected


def test_demo_writes_report(capture, tmp_path, capsys):
    main(["demo", "--data", str(capture), "--out", str(tmp_path), "--iterations", "2", "--augment", "none",
          "--regime", "views=2,lights=1", "--quiet"])
    report = (tmp_path / "report.md").read_text()
    for method in ("| SSS-3DGS (real images only) | 2 |", "| DIAMOND-SSS (full pipeline) | 2 |",
                   "| dense reconstruction |"):
        assert method in report
    assert (tmp_path / "comparison.png").is_file()
    stages = json.loads((tmp_path / "diamond" / "pipeline.json").read_text())["stages"]
    assert list(stages) == ["final", "eval"] and stages["final"]["real_share"] == 1.0
    assert "PSNR" in capsys.readouterr().out


def test_demo_trains_the_dense_reconstruction_in_a_second_process_with_the_same_result(capture, tmp_path,
                                                                                      monkeypatch, capsys):
    from diamond_sss.experiments import demo

    monkeypatch.setattr(demo, "usable_cores", lambda: 2)
    args = ["demo", "--data", str(capture), "--augment", "none", "--regime", "views=2,lights=1", "--iterations", "3"]
    main([*args, "--out", str(tmp_path / "parallel")])
    assert re.search(r"dense reconstruction \(second process\): 100%.* 3/3", capsys.readouterr().err)
    main([*args, "--out", str(tmp_path / "sequential"), "--no-parallel", "--quiet"])
    models = [load_file(tmp_path / mode / "dense" / "model.safetensors") for mode in ("parallel", "sequential")]
    assert models[0].keys() == models[1].keys()
    for name, tensor in models[0].items():
        torch.testing.assert_close(tensor, models[1][name], rtol=1e-5, atol=1e-6, msg=name)
    dense = [json.loads((tmp_path / mode / "dense" / "eval_test" / "metrics.json").read_text())
             for mode in ("parallel", "sequential")]
    # the metrics' float32 CPU reductions may sum in another order in another process (seen on a 16-core machine:
    # SSIM 0.34429011 vs 0.34429013 from the same model), so they agree to 1e-6, not to the last bit
    for key in ("psnr", "ssim", "masked_psnr", "mask_iou"):
        assert dense[0][key] == pytest.approx(dense[1][key], rel=1e-6), key


def test_demo_reuses_finished_runs_and_moves_aside_runs_made_with_other_settings(capture, tmp_path, capsys):
    args = ["demo", "--data", str(capture), "--out", str(tmp_path), "--augment", "none",
            "--regime", "views=2,lights=1", "--quiet", "--no-dense"]
    main([*args, "--iterations", "2"])
    summary = tmp_path / "sss3dgs" / "train_summary.json"
    written = summary.stat().st_mtime_ns
    main([*args, "--iterations", "2"])  # finished: reused, not retrained
    assert summary.stat().st_mtime_ns == written and "moved aside" not in capsys.readouterr().out
    main([*args, "--iterations", "3"])  # another schedule: the old run is kept aside, a new one is made
    assert "moved aside" in capsys.readouterr().out
    aside = [p for p in tmp_path.iterdir() if p.name.startswith("sss3dgs.")]
    assert len(aside) == 1 and (aside[0] / "model.safetensors").is_file()
    assert json.loads(summary.read_text())["steps"] == 3
