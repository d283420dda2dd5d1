"""One save/load and one config.json layout for both diffusion models; the older layouts still load."""

import json
import shutil

import pytest
import torch
from tiny_models import TINY_NVS

from diamond_sss.cli.main import main
from diamond_sss.diffusion.common.model_io import (
    CONFIG_NAME,
    WEIGHTS_NAME,
    blend_model_folders,
    interpolate_weights,
)
from diamond_sss.diffusion.common.paths import shipped_model_dir
from diamond_sss.diffusion.nvs.config import NVSConfig
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


def test_interpolated_weights_are_the_weighted_mean_in_the_first_models_dtypes():
    first = {"w": torch.tensor([1.0, -2.0], dtype=torch.float16), "b": torch.tensor([0.5]), "n": torch.tensor([3])}
    second = {"w": torch.tensor([3.0, 2.0], dtype=torch.float16), "b": torch.tensor([1.5]), "n": torch.tensor([3])}
    blended = interpolate_weights(first, second, 0.25)
    assert blended["w"].dtype == torch.float16 and blended["w"].tolist() == [1.5, -1.0]
    assert blended["b"].tolist() == [0.75] and blended["n"].tolist() == [3]
    for weight, expected in ((0.0, first), (1.0, second)):
        ends = interpolate_weights(first, second, weight)
        assert all(torch.equal(ends[k], expected[k]) for k in expected)


@pytest.mark.parametrize(("second", "weight", "message"), [
    ({"w": torch.zeros(2), "n": torch.tensor([3]), "x": torch.zeros(1)}, 0.5, "in one only: \\['x'\\]"),
    ({"w": torch.zeros(3), "n": torch.tensor([3])}, 0.5, "'w' has shape \\(2,\\) in one model and \\(3,\\)"),
    ({"w": torch.zeros(2), "n": torch.tensor([4])}, 0.5, "'n' is not floating point and differs"),
    ({"w": torch.zeros(2), "n": torch.tensor([3])}, 1.5, "weight must be a number in \\[0, 1\\], got 1.5"),
    ({"w": torch.zeros(2), "n": torch.tensor([3])}, float("nan"), "got nan"),
])
def test_weights_that_cannot_blend_are_named(second, weight, message):
    with pytest.raises(ValueError, match=message):
        interpolate_weights({"w": torch.ones(2), "n": torch.tensor([3])}, second, weight)


def test_two_model_folders_blend_into_a_loadable_model_from_the_command_line(tmp_path):
    config = NVSConfig(**TINY_NVS)
    folders = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        folders.append(NVSModel(config).save(tmp_path / f"model{seed}", half=True))
    main(["blend-models", str(folders[0]), str(folders[1]), "--out", str(tmp_path / "blend"), "--weight", "0.25"])
    blend = NVSModel.load(tmp_path / "blend")
    first, second = (NVSModel.load(folder).state_dict() for folder in folders)
    assert blend.config == config
    for key, value in blend.state_dict().items():
        if key in first and value.is_floating_point():
            expected = torch.lerp(first[key], second[key], 0.25).half().float()
            assert torch.equal(value, expected), key
    torch.manual_seed(2)
    other = NVSModel(NVSConfig(**{**TINY_NVS, "image_size": TINY_NVS["image_size"] * 2})).save(tmp_path / "other")
    with pytest.raises(ValueError, match="differ in \\['config'\\]: only models of one architecture"):
        blend_model_folders(folders[0], other, 0.5, tmp_path / "bad")
    with pytest.raises(ValueError, match="is one of the models blended"):
        blend_model_folders(folders[0], folders[1], 0.5, folders[0])
    with pytest.raises(FileNotFoundError, match="has no config.json"):
        blend_model_folders(folders[0], tmp_path / "missing", 0.5, tmp_path / "bad")
