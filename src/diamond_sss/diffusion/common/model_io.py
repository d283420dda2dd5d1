"""One folder layout and one save/load for both diffusion models: ``config.json`` + ``model.safetensors``.

``config.json``::

    {"model": "nvs" | "relight", "config": {the model's config}, "components": {"unet": {diffusers config}, ...}}

``components`` holds the diffusers configs a model's networks are rebuilt from (empty for the novel-view model,
which builds them from its config). Folders written before this layout (the novel-view config at the top level;
the relighting model's ``{"relight", "unet", "controlnet", "vae"}``) are read through each model's ``legacy``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path

import torch
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


def interpolate_weights(first: dict[str, Tensor], second: dict[str, Tensor], weight: float) -> dict[str, Tensor]:
    """``(1 - weight) * first + weight * second`` for each floating tensor, computed in float32 and stored in
    ``first``'s dtype; other tensors must be equal. Between a model and its fine-tune this trades what the fine-tune
    learnt against what it lost (WiSE-FT, Wortsman et al. 2022). ``weight`` in [0, 1]; both hold the same keys and
    shapes."""
    if not (isinstance(weight, (int, float)) and math.isfinite(weight) and 0 <= weight <= 1):
        raise ValueError(f"weight must be a number in [0, 1], got {weight!r}")
    if first.keys() != second.keys():
        only = sorted(first.keys() ^ second.keys())
        raise ValueError(f"the two models hold different tensors (in one only: {only[:5]})")
    blended = {}
    for key, a in first.items():
        b = second[key]
        if a.shape != b.shape:
            raise ValueError(f"tensor {key!r} has shape {tuple(a.shape)} in one model and {tuple(b.shape)} in the other")
        if a.is_floating_point():
            blended[key] = torch.lerp(a.float(), b.float(), weight).to(a.dtype)
        elif torch.equal(a, b):
            blended[key] = a
        else:
            raise ValueError(f"tensor {key!r} is not floating point and differs between the models")
    return blended


def blend_model_folders(first: str | os.PathLike, second: str | os.PathLike, weight: float,
                        out: str | os.PathLike) -> Path:
    """Write ``interpolate_weights`` of two model folders of one architecture (equal ``config.json``) to ``out``,
    with their config; ``out`` may not be either input."""
    first, second, out = Path(first), Path(second), Path(out)
    configs = []
    for folder in (first, second):
        for name in (CONFIG_NAME, WEIGHTS_NAME):
            if not (folder / name).is_file():
                raise FileNotFoundError(f"model folder {folder} has no {name}")
        try:
            configs.append(json.loads((folder / CONFIG_NAME).read_text()))
        except json.JSONDecodeError as error:
            raise ValueError(f"{folder / CONFIG_NAME} is not valid JSON ({error})") from error
    if configs[0] != configs[1]:
        differing = sorted(key for key in configs[0].keys() | configs[1].keys()
                           if configs[0].get(key) != configs[1].get(key))
        raise ValueError(f"{first / CONFIG_NAME} and {second / CONFIG_NAME} differ in {differing}: "
                         "only models of one architecture and layout blend")
    if out.resolve() in (first.resolve(), second.resolve()):
        raise ValueError(f"the output folder {out} is one of the models blended: write the blend to a new folder")
    state = interpolate_weights(load_safetensors(first / WEIGHTS_NAME), load_safetensors(second / WEIGHTS_NAME),
                                weight)
    atomic_save_safetensors(out / WEIGHTS_NAME, state)
    atomic_write_json(out / CONFIG_NAME, configs[0])
    return out
