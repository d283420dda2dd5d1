"""Damaged files: truncated safetensors and corrupt JSON name the file; resume falls back to an intact
checkpoint; written safetensors are verified before they replace the old file."""

from __future__ import annotations

import json
import logging
import re
import shutil

import pytest
import torch

from diamond_sss.cli.main import main
from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture_with_test_split
from diamond_sss.errors import DamagedFileError, DataError
from diamond_sss.training.checkpoint import checkpoint_folders, load_checkpoint, resume_checkpoint
from diamond_sss.training.overrides import load_run_config, make_config
from diamond_sss.training.trainer import ImageSource, Trainer
from diamond_sss.utils import io as io_module
from diamond_sss.utils.io import atomic_save_safetensors, load_safetensors, read_json

TINY = {"num_gaussians": 200, "batch_size": 1, "lambda_lpips": 0.0, "raytrace_gaussians": 32, "raytrace_every": 2,
        "mv_pixels_per_pair": 16, "mv_pairs_per_step": 1, "densify": False, "log_every": 1,
        "image_log_every": 1000, "device": "cpu"}


def truncate(path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return make_capture_with_test_split(tmp_path_factory.mktemp("capture"), views=4, lights=2, size=12, test_lights=1)


@pytest.fixture(scope="module")
def trained(capture, tmp_path_factory):
    run = tmp_path_factory.mktemp("run") / "run"
    sets = [arg for key, value in TINY.items() for arg in ("--set", f"{key}={value}")]
    main(["train", "--data", str(capture), "--out", str(run), "--iterations", "5", "--quiet",
          "--set", "checkpoint_every=2", *sets])
    return run


def copy_run(run, tmp_path):
    target = tmp_path / "run"
    shutil.copytree(run, target)
    return target


@pytest.mark.parametrize("keep", [0.5, 0.02, 0.0])
def test_truncated_safetensors_names_the_file(tmp_path, keep):
    path = atomic_save_safetensors(tmp_path / "model.safetensors", {"w": torch.arange(1000.0)})
    truncate(path, keep)
    with pytest.raises(DamagedFileError, match=r"model\.safetensors: damaged or truncated safetensors file"):
        load_safetensors(path)
    with pytest.raises(DataError, match=r"absent\.safetensors: file is missing"):
        load_safetensors(tmp_path / "absent.safetensors")


def test_corrupt_json_names_the_file(tmp_path):
    path = tmp_path / "state.json"
    path.write_text('{"step": 3\n"dir": 1}')
    with pytest.raises(DamagedFileError, match=r"state\.json: damaged or invalid JSON \(Expecting ','"):
        read_json(path)
    path.write_bytes(b"\xff\xfe{")
    with pytest.raises(DamagedFileError, match=r"state\.json: damaged or invalid JSON"):
        read_json(path)


def test_written_safetensors_are_verified_before_replacing(tmp_path, monkeypatch):
    path = atomic_save_safetensors(tmp_path / "model.safetensors", {"w": torch.ones(3)})
    real_save = io_module.save_file

    def short_write(tensors, filename, metadata=None):
        real_save(tensors, filename, metadata=metadata)
        truncate(io_module.Path(filename))

    monkeypatch.setattr(io_module, "save_file", short_write)
    with pytest.raises(DamagedFileError, match=r"model\.safetensors: written safetensors file does not read back"):
        atomic_save_safetensors(path, {"w": torch.zeros(3)})
    assert torch.equal(load_safetensors(path)["w"], torch.ones(3))  # the old file is untouched
    assert [p.name for p in tmp_path.iterdir()] == ["model.safetensors"]


@pytest.mark.parametrize("name, damage, message", [
    ("model.safetensors", truncate, r"model\.safetensors: damaged or truncated safetensors file"),
    ("config.json", lambda p: p.write_text("{"), r"config\.json: damaged or invalid JSON"),
    ("config.json", lambda p: p.write_text('{"lambda_mask": "x"}'), r"config\.json: config key 'lambda_mask'"),
])
def test_cli_reports_a_damaged_run_file_in_one_line(trained, tmp_path, capsys, name, damage, message):
    run = copy_run(trained, tmp_path)
    damage(run / name)
    for argv in (["export", "--run", str(run), "--ply", str(tmp_path / "x.ply")],
                 ["eval", "--run", str(run), "--data", str(run), "--json"]):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith("diamond-sss: error: ")
        assert str(run / name) in err
        assert re.search(message, err)


@pytest.mark.parametrize("damaged_file", ["scene.safetensors", "optim.safetensors", "state.json"])
def test_resume_falls_back_to_the_newest_intact_checkpoint(trained, capture, tmp_path, caplog, damaged_file):
    run = copy_run(trained, tmp_path)
    folders = checkpoint_folders(run)
    assert [f.name for f in folders] == ["step_00000004", "step_00000002"]
    truncate(folders[0] / damaged_file)
    with caplog.at_level(logging.WARNING):
        folder, loaded = resume_checkpoint(run)
    assert folder.name == "step_00000002" and loaded.step == 2
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert f"step_00000004 is damaged: {folders[0] / damaged_file}" in warnings[0]
    assert warnings[1] == f"resuming from {folders[1]}, the newest intact checkpoint"
    cfg = make_config("diamond", overrides={**load_run_config(run).flat(), "iterations": 6})  # the run's settings
    with caplog.at_level(logging.INFO, logger="diamond_sss.training.trainer"):
        result = Trainer(cfg, [ImageSource(OLATDataset(capture))], run, show_progress=False).run(resume=True)
    assert f"resuming from step 2 ({folders[1]})" in caplog.text
    history = json.loads((run / "train_summary.json").read_text())["history"]
    assert result.steps == 6 and [h["step"] for h in history] == [1, 2, 3, 4, 5, 6]


def test_corrupt_latest_json_is_named_and_the_folders_are_used(trained, tmp_path, caplog):
    run = copy_run(trained, tmp_path)
    (run / "checkpoints" / "latest.json").write_text('{"step": 4,')
    with caplog.at_level(logging.WARNING):
        folder, loaded = resume_checkpoint(run)
    assert folder.name == "step_00000004" and loaded.step == 4
    assert any(r.getMessage().startswith(f"{run / 'checkpoints' / 'latest.json'}: damaged or invalid JSON")
               for r in caplog.records)


def test_every_checkpoint_damaged_is_an_error_naming_them(trained, tmp_path):
    run = copy_run(trained, tmp_path)
    for folder in checkpoint_folders(run):
        truncate(folder / "scene.safetensors")
    with pytest.raises(DamagedFileError, match=r"checkpoints: no intact checkpoint .*step_00000004.*step_00000002"):
        resume_checkpoint(run)
    (checkpoint_folders(run)[0] / "state.json").write_text('{"optimizers": {}}')
    with pytest.raises(DamagedFileError, match=r"state\.json: expected 'step' and 'optimizers'"):
        load_checkpoint(checkpoint_folders(run)[0])
