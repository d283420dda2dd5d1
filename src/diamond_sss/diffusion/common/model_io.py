"""One folder layout and one save/load for both diffusion models: ``config.json`` + ``model.safetensors``.

``config.json``::

    {"model": "nvs" | "relight", "config": {the model's config}, "components": {"unet": {diffusers config}, ...}}

``components`` holds the diffusers configs a model's networks are rebuilt from (empty for the novel-view model,
which builds them from its config). Folders written before this layout (the novel-view config at the top level;
the relighting model's ``{"relight", "unet", "controlnet", "vae"}``) are read through each model's ``legacy``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

from torch import Tensor, nn

from diamond_sss.utils.io import atomic_save_safetensors, atomic_write_json, load_safetensors

CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"


def save_model(folder: str | os.PathLike, kind: str, config: dict, state: dict[str, Tensor],
               components: dict | None = None, half: bool = False) -> Path:
    """Write ``state`` (floats in fp16 with ``half``) and the config of a ``kind`` model atomically into ``folder``."""
    folder = Path(folder)
    tensors = {k: (v.half() if half and v.is_floating_point() else v).detach().cpu().contiguous()
               for k, v in state.items()}
    atomic_save_safetensors(folder / WEIGHTS_NAME, tensors)
    atomic_write_json(folder / CONFIG_NAME, {"model": kind, "config": config, "components": components or {}})
    return folder


def read_model_config(folder: str | os.PathLike, kind: str, legacy: Callable[[dict], dict]) -> tuple[dict, dict]:
    """``(config, components)`` of the ``kind`` model in ``folder``; ``legacy`` turns a ``config.json`` of an older
    layout into ``{"config": ..., "components": ...}``."""
    folder = Path(folder)
    for name in (CONFIG_NAME, WEIGHTS_NAME):
        if not (folder / name).is_file():
            raise FileNotFoundError(f"{kind} model folder {folder} has no {name}")
    path = folder / CONFIG_NAME
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON ({error})") from error
    if not isinstance(data, dict):
        raise ValueError(f"{path} must hold a JSON object")  # noqa: TRY004 (bad file content)
    if not {"model", "config"} <= set(data):
        try:
            data = {"model": kind, **legacy(data)}
        except KeyError as error:
            raise ValueError(f"{path}: not a {kind} model's config (no 'model' and 'config', nor the older layout's "
                             f"{error})") from error
    if data["model"] != kind:
        raise ValueError(f"{path} holds a {data['model']!r} model, not a {kind!r} one")
    return data["config"], data.get("components") or {}


def load_weights(module: nn.Module, folder: str | os.PathLike, skip_prefix: str | None = None) -> None:
    """Load ``folder/model.safetensors`` into ``module`` as float32; keys under ``skip_prefix`` (a frozen part not
    stored, such as the novel-view model's VAE) may be missing, nothing else."""
    path = Path(folder) / WEIGHTS_NAME
    state = {k: v.float() if v.is_floating_point() else v for k, v in load_safetensors(path).items()}
    missing, unexpected = module.load_state_dict(state, strict=False)
    missing = [k for k in missing if skip_prefix is None or not k.startswith(skip_prefix)]
    if missing or unexpected:
        raise ValueError(f"{path}: missing keys {missing[:5]}, unexpected {unexpected[:5]}")
