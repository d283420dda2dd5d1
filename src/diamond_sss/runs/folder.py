"""A finished run folder: its configuration (``config.json``) and trained scene (``model.safetensors``).

Only the configuration schema and the scene's I/O are imported here, not the training loop.
"""

from __future__ import annotations

from pathlib import Path

import torch

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.scene.io import read_scene
from diamond_sss.scene.model import RelightableScene, SceneRender
from diamond_sss.training.config import TrainConfig
from diamond_sss.training.overrides import load_run_config


def load_scene(run_dir: Path, device: str | torch.device = "cpu") -> tuple[RelightableScene, TrainConfig]:
    """The trained scene and configuration of a run folder."""
    cfg = load_run_config(run_dir)
    path = Path(run_dir) / "model.safetensors"
    if not path.is_file():
        raise ValueError(f"{run_dir}: no trained model ({path} is missing; is the run finished?)")
    return read_scene(path, cfg.shading, device), cfg


def render_lattice_image(scene: RelightableScene, lattice: OLATDataset, view: int, light: int,
                         scale: float = 1.0) -> SceneRender:
    """``scene`` rendered (no gradient) at camera ``view`` of ``lattice`` under its light ``light``; ``scale`` < 1
    renders the camera's image resized by it (:meth:`~diamond_sss.data.dataset.Camera.resized`)."""
    camera, lit, device = lattice.cameras[view].resized(scale), lattice.lights[light], scene.gaussians.means.device
    with torch.no_grad():
        return scene.render(camera.w2c[None].to(device), camera.K[None].to(device), camera.width, camera.height,
                            lit.position[None].to(device), lit.intensity[None].to(device))
