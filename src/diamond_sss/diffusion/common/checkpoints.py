"""Atomic, resumable checkpoints of the diffusion fine-tunes: ``accelerator.save_state`` plus ``extra.json`` in
``<root>/step_<N>`` (:mod:`diamond_sss.utils.step_folders`).

A checkpoint folder is written under a temporary name and renamed into place, so a kill at any moment leaves the
previous checkpoint usable.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from diamond_sss.utils.io import atomic_write_json, read_json
from diamond_sss.utils.step_folders import step_folder_name, step_folders

if TYPE_CHECKING:
    from accelerate import Accelerator


def save_accelerate_checkpoint(
    accelerator: Accelerator, root: str | os.PathLike, step: int, extra: dict | None = None, keep: int = 2
) -> Path | None:
    """Save models, optimizers, schedulers, RNG states and registered objects as ``root/step_<step>``.

    Every process calls ``accelerator.save_state`` into one temporary folder (each writes its own RNG state,
    so a resumed multi-process run draws what it would have drawn), which the main process renames into place
    once complete; then only the ``keep`` newest checkpoints are kept (0: every one). ``extra`` (JSON) is stored as
    ``extra.json``. Returns the folder on the main process, ``None`` elsewhere.
    """
    root = Path(root)
    final = root / step_folder_name(step)
    tmp = root / f".{final.name}.tmp"
    if accelerator.is_main_process:
        root.mkdir(parents=True, exist_ok=True)
        if tmp.exists():
            shutil.rmtree(tmp)
    accelerator.wait_for_everyone()
    try:
        accelerator.save_state(str(tmp), safe_serialization=True)
        accelerator.wait_for_everyone()
        if not accelerator.is_main_process:
            return None
        atomic_write_json(tmp / "extra.json", {"step": step, **(extra or {})})
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    finally:
        if accelerator.is_main_process and tmp.exists():
            shutil.rmtree(tmp)
    for old in step_folders(root, "extra.json")[:-keep] if keep > 0 else []:
        shutil.rmtree(old)
    return final


def latest_accelerate_checkpoint(root: str | os.PathLike) -> Path | None:
    """Newest complete ``step_<N>`` folder under ``root`` (temporary folders are ignored)."""
    found = step_folders(Path(root), "extra.json")
    return found[-1] if found else None


def load_accelerate_checkpoint(accelerator: Accelerator, folder: str | os.PathLike) -> dict:
    """Restore everything ``save_accelerate_checkpoint`` saved; returns the ``extra.json`` content (with ``step``)."""
    folder = Path(folder)
    if not (folder / "extra.json").is_file():
        raise FileNotFoundError(f"{folder} is not a complete checkpoint (no extra.json)")
    accelerator.load_state(str(folder))
    return read_json(folder / "extra.json")
