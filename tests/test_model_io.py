"""One save/load and one config.json layout for both diffusion models; the older layouts still load."""

import json
import shutil

import pytest
import torch

from diamond_sss.diffusion.common.model_io import CONFIG_NAME, WEIGHTS_NAME
from diamond_sss.diffusion.common.paths import shipped_model_dir
from diamond_sss.diffusion.nvs.model import NVSModel
from diamond_sss.diffusion.relight.model import RelightDiffusion

MODELS = {"nvs": NVSModel, "relight": RelightDiffusion}


def _older_layout(kind: str, layout: dict) -> dict:
    """The config.json the shipped model had before the common layout."""
    if kind == "nvs":
        return layout["config"]
    return {"relight": layout["config"], **layout["components"]}


def _same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    first, second = a.state_dict(), b.state_dict()
    return first.keys() == second.keys() and all(torch.equal(first[k], second[k]) for k in first)


@pytest.mark.parametrize("kind", sorted(MODELS))
def test_the_shipped_model_has_the_common_layout_and_its_older_layout_loads_the_same(kind, tmp_path):
    shipped = shipped_model_dir(kind)
    layout = json.loads((shipped / CONFIG_NAME).read_text())
    assert layout["model"] == kind and set(layout) == {"model", "config", "components"}
    model = MODELS[kind].load(shipped)
    older = tmp_path / "older"
    older.mkdir()
    shutil.copyfile(shipped / WEIGHTS_NAME, older / WEIGHTS_NAME)
    (older / CONFIG_NAME).write_text(json.dumps(_older_layout(kind, layout)))
    again = MODELS[kind].load(older)
    assert again.config == model.config and _same_weights(model, again)
    saved = json.loads((model.save(tmp_path / "saved") / CONFIG_NAME).read_text())
    assert saved == layout


def test_a_folder_of_the_other_model_or_no_model_is_named(tmp_path):
    with pytest.raises(ValueError, match="holds a 'relight' model, not a 'nvs' one"):
        NVSModel.load(shipped_model_dir("relight"))
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / WEIGHTS_NAME).write_bytes(b"")
    with pytest.raises(FileNotFoundError, match=f"relight model folder {folder} has no config.json"):
        RelightDiffusion.load(folder)
    (folder / CONFIG_NAME).write_text("{")
    with pytest.raises(ValueError, match="config.json is not valid JSON"):
        RelightDiffusion.load(folder)
    (folder / CONFIG_NAME).write_text('{"unet": {}}')
    with pytest.raises(ValueError, match=r"config.json: not a relight model's config .*'relight'"):
        RelightDiffusion.load(folder)
    (folder / CONFIG_NAME).write_text('{"image_size": 32, "colour": 1}')
    with pytest.raises(ValueError, match=r"config.json: unknown NVS config keys \['colour'\]"):
        NVSModel.load(folder)
