"""A scene's tensors and its ``model.safetensors`` file (the same names as ``RelightableScene.state_dict``)."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import torch
from torch import Tensor

from diamond_sss.gaussians.model import GaussianModel
from diamond_sss.scene.model import RelightableScene
from diamond_sss.utils.io import atomic_save_safetensors, load_safetensors

SCENE_FORMAT = "diamond-sss-scene-v1"


class SceneSettings(Protocol):
    """The configuration keys a scene is built with (``TrainConfig.shading`` has them)."""

    sss_width: int
    sss_position_freqs: int
    light_init: float
    mixed_precision: bool
    light_falloff: str
    sss_angular_inputs: bool
    sss_light_depth: int
    sss_visibility_gradient: bool


def scene_tensors(scene: RelightableScene) -> dict[str, Tensor]:
    """All scene tensors by ``state_dict`` name (Gaussians, MLP, light scale)."""
    return {k: v.detach() for k, v in scene.state_dict().items()}


def scene_from_tensors(tensors: dict[str, Tensor], cfg: SceneSettings) -> RelightableScene:
    """Rebuild a scene from :func:`scene_tensors` (Gaussian count taken from the tensors)."""
    prefix = "gaussians.params."
    model = GaussianModel.from_state_tensors({k[len(prefix):]: v for k, v in tensors.items()
                                              if k.startswith(prefix)})
    scene = RelightableScene(model, sss_width=cfg.sss_width, sss_position_freqs=cfg.sss_position_freqs,
                             light_init=cfg.light_init,
                             mixed_precision=cfg.mixed_precision, light_falloff=cfg.light_falloff,
                             sss_angular_inputs=cfg.sss_angular_inputs, sss_light_depth=cfg.sss_light_depth,
                             sss_visibility_gradient=cfg.sss_visibility_gradient)
    scene.load_state_dict(tensors)
    return scene


def save_scene(path: Path, scene: RelightableScene) -> Path:
    """The trained scene as one safetensors file."""
    return atomic_save_safetensors(path, scene_tensors(scene), metadata={"format": SCENE_FORMAT})


def read_scene(path: Path, cfg: SceneSettings, device: str | torch.device = "cpu") -> RelightableScene:
    """The scene saved by :func:`save_scene` in ``path``, built with ``cfg``'s settings, on ``device``."""
    return scene_from_tensors(load_safetensors(path), cfg).to(device)
