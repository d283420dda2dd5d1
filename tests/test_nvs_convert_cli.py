"""diamond-sss convert-free3d: the official checkpoint becomes a model folder NVSModel loads."""

from __future__ import annotations

import re

import pytest
import torch
from test_nvs_convert import official_free3d_shapes, tiny_free3d_config

from diamond_sss.cli.main import main
from diamond_sss.cli.nvs_commands import write_free3d_model
from diamond_sss.diffusion.nvs.model import NVSModel
from diamond_sss.utils.io import load_safetensors


@pytest.fixture
def checkpoint(tmp_path):
    g = torch.Generator().manual_seed(0)
    state = {k: torch.randn(shape, generator=g) for k, shape in official_free3d_shapes().items()}
    path = tmp_path / "free3d.ckpt"
    torch.save({"state_dict": state}, path)
    return path, state


def test_converted_folder_loads_with_the_official_weights(checkpoint, tmp_path):
    path, state = checkpoint
    folder, count = write_free3d_model(path, tmp_path / "model", tiny_free3d_config(), seed=3)
    assert count == len(state) - 3  # the VAE, CLIP and schedule keys are left out
    model = NVSModel.load(folder)  # strict: every key of the model is in the file
    ours = model.state_dict()
    torch.testing.assert_close(ours["unet.down_blocks.1.resnets.0.ray_proj.weight"],
                               state["model.diffusion_model.input_blocks.4.0.pose_layers.0.weight"])
    assert torch.equal(ours["null_embedding"], torch.zeros_like(ours["null_embedding"]))
    again, _ = write_free3d_model(path, tmp_path / "again", tiny_free3d_config(), seed=3)
    other, _ = write_free3d_model(path, tmp_path / "other", tiny_free3d_config(), seed=4, half=True)
    a, b, c = (load_safetensors(f / "model.safetensors") for f in (folder, again, other))
    assert all(torch.equal(a[k], b[k]) for k in a)
    encoder_key = next(k for k in a if k.startswith("reference_encoder.") and k.endswith("weight"))
    assert not torch.equal(a[encoder_key].half(), c[encoder_key]) and c[encoder_key].dtype == torch.float16


@pytest.mark.parametrize("damage, message", [
    (lambda path, state: path.unlink(), "Free3D checkpoint .*free3d.ckpt not found"),
    (lambda path, state: torch.save({"state_dict": {**state, "model.other.weight": torch.zeros(1)}}, path),
     "free3d.ckpt: not an official Free3D checkpoint"),
    (lambda path, state: path.write_bytes(path.read_bytes()[:200]), "free3d.ckpt: damaged or unreadable checkpoint"),
])
def test_cli_refuses_missing_foreign_or_damaged_checkpoints(checkpoint, tmp_path, capsys, damage, message):
    path, state = checkpoint
    damage(path, state)
    with pytest.raises(SystemExit):
        main(["convert-free3d", str(path), str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert re.search(message, err) and not (tmp_path / "out").exists()
