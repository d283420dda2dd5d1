"""Test helpers that edit a copy of a capture on disk."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import imageio.v3 as iio


def copy_with_mask_files(source: Path, dest: Path, split: str = "train") -> Path:
    """Copy the capture ``source`` to ``dest`` with each image's alpha also written as a ``_mask.png`` file that
    ``transforms_<split>.json`` names in ``mask_paths``; returns ``dest``."""
    shutil.copytree(source, dest)
    path = dest / f"transforms_{split}.json"
    transforms = json.loads(path.read_text())
    for frame in transforms["frames"]:
        frame["mask_paths"] = [name.replace(".png", "_mask.png") for name in frame["file_paths"]]
        for image, mask in zip(frame["file_paths"], frame["mask_paths"]):
            iio.imwrite(dest / mask, iio.imread(dest / image)[..., 3])
    path.write_text(json.dumps(transforms))
    return dest
