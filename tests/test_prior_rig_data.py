"""scripts/make_prior_rig_data.py: the random rigs frame as stated, are reproducible, and spare every judge."""

from __future__ import annotations

import math
import re

import pytest
from repo_scripts import ROOT, load_script

from diamond_sss.diffusion.nvs.canonical import PRIOR_CAMERA_RADIUS, PRIOR_FOV_X_DEG, PRIOR_FRAME_FILL

rig_data = load_script("scripts/make_prior_rig_data.py")


def test_field_of_view_reproduces_the_priors_rig():
    assert rig_data.field_of_view_deg(PRIOR_CAMERA_RADIUS, PRIOR_FRAME_FILL) == pytest.approx(PRIOR_FOV_X_DEG)
    # A sphere at distance 2 subtends 60 degrees: filling the whole width needs exactly that field of view.
    assert rig_data.field_of_view_deg(2.0, 1.0) == pytest.approx(60.0)


def test_rigs_are_seeded_and_within_their_ranges():
    seeds = [seed for _, _, seed in rig_data.captures("relight")]
    rigs = [rig_data.sample_rig(seed) for seed in seeds]
    assert rigs == [rig_data.sample_rig(seed) for seed in seeds]
    assert len({r["camera_radius"] for r in rigs}) == len(rigs)
    for rig in rigs:
        fill = math.tan(math.asin(1 / rig["camera_radius"])) / math.tan(math.radians(rig["fov_x_deg"]) / 2)
        assert fill == pytest.approx(rig["fill"], abs=2e-3)
        assert rig_data.FILL_RANGE[0] <= rig["fill"] <= rig_data.FILL_RANGE[1]
        assert rig_data.FOV_RANGE_DEG[0] <= rig["fov_x_deg"] <= rig_data.FOV_RANGE_DEG[1]
        assert rig_data.CAMERA_RADIUS_RANGE[0] <= rig["camera_radius"] <= rig_data.CAMERA_RADIUS_RANGE[1]
        assert rig_data.LIGHT_RADIUS_RANGE[0] <= rig["light_radius"] <= rig_data.LIGHT_RADIUS_RANGE[1]
        assert rig["camera_band"][0] < rig["camera_band"][1] and rig["light_band"][0] < rig["light_band"][1]


def _pairs(text: str) -> set[str]:
    return {f"{shape}:{material}" for shape, material in re.findall(r"\b(blob|bunny|bust|knot|sphere|torus):([a-z_]+):\d+", text)}


def test_no_capture_is_a_judge_or_benchmark_object():
    heldout = _pairs((ROOT / "scripts" / "make_heldout_data.sh").read_text())
    relight_judges = _pairs((ROOT / "benchmarks" / "relight_quality.py").read_text())
    relight_validation = {"blob:jade", "bunny:skin", "bust:soap", "sphere:glazed_wax"}
    benchmark = {"bunny:wax", "torus:soap", "blob:marble", "bust:jade"}
    novel_view_judges = {"torus:marble", "bunny:soap", "blob:jade"}  # benchmarks/nvs_quality.py, judge_prior.sh
    assert len(heldout) >= 13 and len(relight_judges) == 9
    for kind, judges in (("relight", heldout | relight_judges | relight_validation | benchmark),
                         ("novel-view", heldout | novel_view_judges | benchmark)):
        used = {f"{shape}:{material}" for shape, material, _ in rig_data.captures(kind)}
        assert used and not used & judges, (kind, used & judges)
    assert "bunny:soap" in {f"{s}:{m}" for s, m, _ in rig_data.captures("relight")}


def test_an_interpreter_that_does_not_exist_stops_before_anything_is_written(monkeypatch, capsys, tmp_path):
    monkeypatch.setattr(rig_data, "ROOT", tmp_path)
    monkeypatch.setattr("sys.argv", ["make_prior_rig_data.py", "--python", str(tmp_path / "no_python")])
    with pytest.raises(SystemExit) as stop:
        rig_data.main()
    assert stop.value.code == 2 and "--python" in capsys.readouterr().err
    assert not (tmp_path / "outputs").exists()
