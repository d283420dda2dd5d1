"""benchmarks/rounds.py: the rounds of pipeline folders, split at a mask-area threshold."""

from __future__ import annotations

import json
import sys

import pytest
from repo_scripts import load_script

rounds = load_script("benchmarks/rounds.py", "rounds_benchmark")


def pipeline_folder(run, psnrs, ious, area, kept=False, sss=None):
    """A two-round pipeline folder as the pipeline leaves it (metrics and the last round's records)."""
    for folder, psnr, iou in ((run / "round1", psnrs[0], ious[0]), (run, psnrs[1], ious[1])):
        (folder / "final" / "eval_test").mkdir(parents=True)
        (folder / "final" / "eval_test" / "metrics.json").write_text(json.dumps({"psnr": psnr, "mask_iou": iou}))
    final = {"kept": str(run / "round1" / "final")} if kept else {}
    (run / "pipeline.json").write_text(json.dumps(
        {"stages": {"repair": {"mask_area_vs_previous_round": area}, "final": final}}))
    if sss is not None:
        (run.parent / "sss3dgs" / "eval_test").mkdir(parents=True)
        (run.parent / "sss3dgs" / "eval_test" / "metrics.json").write_text(
            json.dumps({"psnr": sss, "mask_iou": 0.9}))
    return run


def test_runs_are_sorted_by_mask_area_and_split_at_the_threshold(tmp_path, monkeypatch, capsys):
    a = pipeline_folder(tmp_path / "a" / "repair", (20.0, 21.0), (0.90, 0.91), 0.96, sss=19.0)
    b = pipeline_folder(tmp_path / "b" / "repair", (25.0, 24.5), (0.95, 0.92), 0.91)
    c = pipeline_folder(tmp_path / "c" / "repair", (22.0, 22.0), (0.93, 0.93), 0.92, kept=True)
    (tmp_path / "single" / "final").mkdir(parents=True)  # one round: no row
    (tmp_path / "single" / "pipeline.json").write_text(json.dumps({"stages": {}}))
    out = tmp_path / "out"
    monkeypatch.setattr(sys, "argv", ["rounds.py", str(a), str(b), str(c), str(tmp_path / "single"),
                                      str(tmp_path / "typo"), "--out", str(out), "--threshold", "0.94"])
    rounds.main()
    printed = capsys.readouterr().out
    assert f"{tmp_path / 'single'}: skipped: no evaluated rounds; two or more are compared" in printed
    assert f"{tmp_path / 'typo'}: skipped: not a pipeline folder (no pipeline.json)" in printed
    report = json.loads((out / "rounds.json").read_text())
    assert [row["run"] for row in report["runs"]] == [str(b), str(c), str(a)]
    below, above = report["summary"]
    assert below["side"] == "below" and below["runs"] == 2 and below["mask_area"] == [0.91, 0.92]
    assert below["psnr_last_minus_first"] == pytest.approx(-0.25)
    assert below["mask_iou_last_minus_first"] == pytest.approx(-0.015)
    assert above["runs"] == 1 and above["psnr_last_minus_first"] == pytest.approx(1.0)
    text = (out / "rounds.md").read_text()
    assert f"| {a} | 19.00 (0.900) | 20.00 (0.900) | 21.00 (0.910) | 0.960 | +1.00 dB, IoU +0.010 |" in text
    assert f"| {c} | - | 22.00 (0.930) | 22.00 (0.930) kept | 0.920 |" in text
    assert "- below: 2 runs, masks 0.910-0.920, last - first round -0.25 dB, mask IoU -0.015" in printed
    monkeypatch.setattr(sys, "argv", ["rounds.py", str(tmp_path / "single"), "--out", str(out)])
    with pytest.raises(SystemExit, match="no pipeline folder given has two evaluated rounds"):
        rounds.main()
    monkeypatch.setattr(sys, "argv", ["rounds.py", str(a), "--out", str(out), "--threshold", "94"])
    with pytest.raises(SystemExit):
        rounds.main()
    assert "--threshold must be in [0, 1], got 94.0" in capsys.readouterr().err
