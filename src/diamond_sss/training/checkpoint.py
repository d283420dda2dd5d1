"""Atomic, resumable checkpoints of the scene trainer in ``step_<N>`` folders
(:mod:`diamond_sss.utils.step_folders`; the diffusion fine-tunes' are in ``diffusion/common/checkpoints.py``).

Layout of ``<run>/checkpoints`` (:func:`save_checkpoint`)::

    step_00000500/scene.safetensors      raw Gaussian parameters, MLP weights, log light scale
    step_00000500/optim.safetensors      Adam moments of every optimiser, keyed ``<optimizer>/<slot>``
    step_00000500/strategy.safetensors   densification accumulators (when present)
    step_00000500/average.safetensors    the running mean of the scene tensors (``schedule.average_last``, when begun)
    step_00000500/state.json             step, optimiser hyperparameters, strategy scalars
    latest.json                          {"step": 500, "dir": "step_00000500"}

A checkpoint folder is written under a temporary name and renamed into place (then ``latest.json`` is
replaced atomically), so a kill at any moment leaves the previous checkpoint usable.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from diamond_sss.errors import DamagedFileError, DataError
from diamond_sss.utils.io import (
    atomic_save_safetensors,
    atomic_write_json,
    default_mode,
    load_safetensors,
    read_json,
)
from diamond_sss.utils.step_folders import step_folder_name, step_folders

logger = logging.getLogger(__name__)


@dataclass
class Checkpoint:
    """A loaded checkpoint."""

    step: int
    scene: dict[str, Tensor]
    optimizers: dict[str, dict]
    strategy: dict
    extra: dict
    average: dict[str, Tensor]


def optimizer_to_tensors(name: str, optimizer: torch.optim.Optimizer) -> tuple[dict[str, Tensor], dict]:
    """Split ``optimizer.state_dict()`` into tensors (for safetensors) and JSON-able hyperparameters.

    The tensors are the optimizer's own, as ``state_dict()`` returns them: write them to a file; loading them into
    another optimizer in the same process would share its moments."""
    state = optimizer.state_dict()
    tensors: dict[str, Tensor] = {}
    scalars: dict[str, dict] = {}
    for index, slots in state["state"].items():
        for slot, value in slots.items():
            key = f"{name}/{index}/{slot}"
            if torch.is_tensor(value):
                tensors[key] = value
            else:
                scalars[key] = value
    return tensors, {"param_groups": state["param_groups"], "scalars": scalars}


def optimizer_from_tensors(name: str, tensors: dict[str, Tensor], meta: dict) -> dict:
    """Inverse of :func:`optimizer_to_tensors`: a state dict for ``optimizer.load_state_dict``."""
    state: dict[int, dict] = {}
    prefix = f"{name}/"
    for key, value in tensors.items():
        if key.startswith(prefix):
            _, index, slot = key.split("/", 2)
            state.setdefault(int(index), {})[slot] = value
    for key, value in meta.get("scalars", {}).items():
        _, index, slot = key.split("/", 2)
        state.setdefault(int(index), {})[slot] = value
    return {"state": state, "param_groups": meta["param_groups"]}


def save_checkpoint(run_dir: Path, step: int, scene_tensors: dict[str, Tensor],
                    optimizers: dict[str, torch.optim.Optimizer], strategy_state: dict, extra: dict,
                    average: dict[str, Tensor] | None = None, keep: int = 2) -> Path:
    """Write checkpoint ``step`` atomically and keep the newest ``keep`` (0: every one; ``average``: the running
    mean of the scene tensors, when there is one)."""
    root = Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    name = step_folder_name(step)
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=root))
    os.chmod(tmp, default_mode(directory=True))
    try:
        atomic_save_safetensors(tmp / "scene.safetensors", scene_tensors)
        optim_tensors: dict[str, Tensor] = {}
        optim_meta: dict[str, dict] = {}
        for opt_name, optimizer in optimizers.items():
            tensors, meta = optimizer_to_tensors(opt_name, optimizer)
            optim_tensors.update(tensors)
            optim_meta[opt_name] = meta
        atomic_save_safetensors(tmp / "optim.safetensors", optim_tensors)
        strategy_tensors = {k: v for k, v in strategy_state.items() if torch.is_tensor(v)}
        strategy_scalars = {k: v for k, v in strategy_state.items() if not torch.is_tensor(v) and v is not None}
        if strategy_tensors:
            atomic_save_safetensors(tmp / "strategy.safetensors", strategy_tensors)
        if average:
            atomic_save_safetensors(tmp / "average.safetensors", average)
        atomic_write_json(tmp / "state.json", {"step": step, "optimizers": optim_meta,
                                               "strategy": strategy_scalars, "extra": extra})
        final = root / name
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    atomic_write_json(root / "latest.json", {"step": step, "dir": name})
    for old in step_folders(root, "state.json")[:-keep] if keep > 0 else []:
        shutil.rmtree(old)
    return final


def checkpoint_folders(run_dir: Path) -> list[Path]:
    """Checkpoint folders of a run, newest first (the one ``latest.json`` names first when it reads)."""
    root = Path(run_dir) / "checkpoints"
    folders = step_folders(root)[::-1]
    pointer = root / "latest.json"
    if pointer.is_file():
        try:
            named = root / str(read_json(pointer)["dir"])
        except DataError as exc:
            logger.warning("%s; looking for checkpoint folders instead", exc)
        except (KeyError, TypeError) as exc:
            logger.warning("%s: no checkpoint folder named (%r); looking for checkpoint folders instead", pointer,
                           exc)
        else:
            folders.sort(key=lambda folder: folder != named)
    return folders


def resume_checkpoint(run_dir: Path) -> tuple[Path, Checkpoint] | None:
    """The newest checkpoint that loads, with its folder; None when there is none.

    A damaged newer checkpoint is skipped with a warning naming the bad file and the one resumed from.
    Raises :class:`DamagedFileError` when every checkpoint is damaged.
    """
    damaged: list[str] = []
    for folder in checkpoint_folders(run_dir):
        try:
            loaded = load_checkpoint(folder)
        except DataError as exc:
            logger.warning("checkpoint %s is damaged: %s", folder.name, exc)
            damaged.append(str(exc))
            continue
        if damaged:
            logger.warning("resuming from %s, the newest intact checkpoint", folder)
        return folder, loaded
    if damaged:
        raise DamagedFileError(f"{Path(run_dir) / 'checkpoints'}: no intact checkpoint ({'; '.join(damaged)})")
    return None


def load_checkpoint(folder: Path) -> Checkpoint:
    """Read a checkpoint folder written by :func:`save_checkpoint`; damaged files raise naming the file."""
    state_path = folder / "state.json"
    meta = read_json(state_path)
    try:
        step, optim_meta = int(meta["step"]), meta["optimizers"]
    except (KeyError, TypeError, ValueError) as exc:
        raise DamagedFileError(f"{state_path}: expected 'step' and 'optimizers' ({exc!r})") from exc
    optim_tensors = load_safetensors(folder / "optim.safetensors")
    optimizers = {name: optimizer_from_tensors(name, optim_tensors, m) for name, m in optim_meta.items()}
    strategy = dict(meta.get("strategy", {}))
    if (folder / "strategy.safetensors").is_file():
        strategy.update(load_safetensors(folder / "strategy.safetensors"))
    average_path = folder / "average.safetensors"
    average = load_safetensors(average_path) if average_path.is_file() else {}
    averaged_steps = meta.get("extra", {}).get("averaged_steps", 0)
    if average and not (isinstance(averaged_steps, int) and averaged_steps > 0):
        raise DamagedFileError(f"{state_path}: expected 'extra.averaged_steps' > 0 beside {average_path}"
                               f", got {averaged_steps!r}")
    if not average and averaged_steps:
        raise DamagedFileError(f"{average_path}: missing or empty, though {state_path} records "
                               f"'extra.averaged_steps' = {averaged_steps!r}")
    return Checkpoint(step=step, scene=load_safetensors(folder / "scene.safetensors"),
                      optimizers=optimizers, strategy=strategy, extra=meta.get("extra", {}), average=average)
