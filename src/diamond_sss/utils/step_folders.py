"""Checkpoint folders named by their step, ``step_<N>`` (``N`` zero-padded to 8 digits; older runs with 7-digit
names are still found and ordered by their number). Shared by the scene trainer's checkpoints
(``training/checkpoint.py``) and the diffusion fine-tunes' (``diffusion/common/checkpoints.py``)."""

from __future__ import annotations

import re
from pathlib import Path

_STEP_DIR = re.compile(r"^step_(\d+)$")


def step_folder_name(step: int) -> str:
    """Name of the checkpoint folder of ``step`` (``step_00000500``)."""
    return f"step_{step:08d}"


def step_folders(root: Path, marker: str | None = None) -> list[Path]:
    """``step_<N>`` folders under ``root`` (holding the file ``marker`` when given), oldest first by ``N`` (any zero
    padding); none when ``root`` is not a folder."""
    if not root.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in root.iterdir() if p.is_dir() and (m := _STEP_DIR.match(p.name))]
    return [p for _, p in sorted(found) if marker is None or (p / marker).is_file()]
