"""Atomic, resumable checkpoints of an ``accelerate`` training loop (``step_<N>`` folders)."""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from pathlib import Path

from accelerate import Accelerator

from diamond_sss.utils.io import atomic_write_json

_STEP_DIR = re.compile(r"^step_(\d+)$")


def save_checkpoint(
    accelerator: Accelerator, root: str | os.PathLike, step: int, extra: dict | None = None, keep: int = 2
) -> Path | None:
    """Save models, optimizers, schedulers, RNG states and registered objects as ``root/step_<step>``.

    ``accelerator.save_state`` writes into a temporary folder that is renamed into place once complete,
    then only the ``keep`` newest checkpoints are kept. ``extra`` (JSON) is stored as ``extra.json``.
    Returns the folder on the main process, ``None`` elsewhere.
    """
    accelerator.wait_for_everyone()
    if not accelerator.is_main_process:
        return None
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    final = root / f"step_{step:08d}"
    tmp = Path(tempfile.mkdtemp(prefix=f".step_{step:08d}.", suffix=".tmp", dir=root))
    try:
        accelerator.save_state(str(tmp), safe_serialization=True)
        atomic_write_json(tmp / "extra.json", {"step": step, **(extra or {})})
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    for old in _checkpoints(root)[:-keep] if keep > 0 else []:
        shutil.rmtree(old)
    return final


def latest_checkpoint(root: str | os.PathLike) -> Path | None:
    """Newest complete ``step_<N>`` folder under ``root`` (temporary folders are ignored)."""
    found = _checkpoints(Path(root))
    return found[-1] if found else None


def load_checkpoint(accelerator: Accelerator, folder: str | os.PathLike) -> dict:
    """Restore everything ``save_checkpoint`` saved; returns the ``extra.json`` content (with ``step``)."""
    folder = Path(folder)
    if not (folder / "extra.json").is_file():
        raise FileNotFoundError(f"{folder} is not a complete checkpoint (no extra.json)")
    accelerator.load_state(str(folder))
    return json.loads((folder / "extra.json").read_text())


def _checkpoints(root: Path) -> list[Path]:
    if not root.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in root.iterdir() if p.is_dir() and (m := _STEP_DIR.match(p.name))]
    return [p for _, p in sorted(found) if (p / "extra.json").is_file()]
