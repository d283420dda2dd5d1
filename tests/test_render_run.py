"""``diamond-sss render`` (evaluation.run.render_run): which cameras and lights each frame is rendered with."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from diamond_sss.data.conventions import look_at_opengl_c2w
from diamond_sss.data.images import write_png
from diamond_sss.evaluation import run as run_module
from diamond_sss.training.overrides import make_config

WIDTH, HEIGHT = 12, 8
LIGHTS = {"a": ([0.0, 0.0, 4.0], [2.0, 2.0, 2.0]), "b": ([4.0, 0.0, 0.0], [1.0, 1.0, 1.0]),
          "c": ([0.0, 4.0, 0.0], [3.0, 3.0, 3.0])}


@pytest.fixture
def capture(tmp_path):
    """A non-square per-image capture of two views whose first images are under different lights of different
    intensities (view 0: a then b, view 1: b then c)."""
    image = np.zeros((HEIGHT, WIDTH, 4), np.uint8)
    image[2:6, 4:8] = 200
    frames = []
    for view, eye, lights in ((0, [3.0, 0.0, 0.5], "ab"), (1, [0.0, 3.0, 0.5], "bc")):
        c2w = look_at_opengl_c2w(torch.tensor(eye), torch.zeros(3)).tolist()
        for light in lights:
            name = f"train/v{view}_{light}.png"
            write_png(tmp_path / name, image)
            position, intensity = LIGHTS[light]
            frames.append({"file_path": name, "transform_matrix": c2w, "pl_pos": position, "pl_intensity": intensity})
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": math.radians(40), "frames": frames}))
    return tmp_path


@pytest.fixture
def renders(monkeypatch):
    """The render calls of a stand-in scene: camera K, image size, light position and intensity."""
    calls = []

    class Scene(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.anchor = torch.nn.Parameter(torch.zeros(1))

        def render(self, w2c, K, width, height, positions, intensities, overrides=None):
            calls.append(SimpleNamespace(K=K[0].cpu(), size=(width, height), position=positions[0].tolist(),
                                         intensity=intensities[0].tolist()))
            return SimpleNamespace(radiance=torch.zeros(1, height, width, 3),
                                   gbuffer=SimpleNamespace(alpha=torch.zeros(1, height, width, 1)))

    monkeypatch.setattr(run_module, "load_scene", lambda run, device: (Scene(), make_config("diamond")))
    return calls


def test_each_view_renders_under_its_first_light_at_the_captures_intensity(capture, tmp_path, renders):
    run_module.render_run(tmp_path / "run", tmp_path / "frames", data=capture, split="train", device="cpu")
    assert [(call.position, call.intensity) for call in renders] == [LIGHTS["a"], LIGHTS["b"]]


def test_given_lights_take_the_given_intensity_in_every_view(capture, tmp_path, renders):
    run_module.render_run(tmp_path / "run", tmp_path / "frames", data=capture, split="train", device="cpu",
                          lights=[1.0, 2.0, 3.0, 0.0, 0.0, 5.0], light_intensity=0.5)
    assert [(call.position, call.intensity) for call in renders] == 2 * [([1.0, 2.0, 3.0], [0.5] * 3),
                                                                         ([0.0, 0.0, 5.0], [0.5] * 3)]


def test_an_orbit_of_a_non_square_capture_is_centred_on_the_object(capture, tmp_path, renders):
    run_module.render_run(tmp_path / "run", tmp_path / "orbit", data=capture, split="train", device="cpu", orbit=2,
                          size=6)
    data_K = run_module.OLATDataset(capture, "train").intrinsics[0]
    assert len(renders) == 2 and (tmp_path / "orbit" / "orbit.gif").is_file()
    for call in renders:
        assert call.size == (6, 6) and (call.position, call.intensity) == LIGHTS["a"]  # the data's first image's
        assert call.K[0, 2].item() == call.K[1, 2].item() == 3.0
        assert call.K[0, 0].item() == pytest.approx(data_K[0, 0].item() * 6 / WIDTH)
        assert call.K[1, 1].item() == pytest.approx(data_K[1, 1].item() * 6 / WIDTH)
