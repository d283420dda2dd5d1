"""Atomic writes: the mode a plain write gives (umask applied), never mkstemp's 0600."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest
import torch

from diamond_sss.data.images import write_png
from diamond_sss.utils.io import (
    atomic_copy_tree,
    atomic_save_safetensors,
    atomic_write_json,
    default_mode,
    load_safetensors,
)


@pytest.mark.parametrize("umask", [0o022, 0o027, 0o077])
def test_atomic_writes_get_the_mode_of_a_plain_write(tmp_path, umask):
    previous = os.umask(umask)
    try:
        plain = tmp_path / "plain.txt"
        plain.write_text("x")
        written = [
            atomic_write_json(tmp_path / "config.json", {"a": 1}),
            atomic_save_safetensors(tmp_path / "model.safetensors", {"w": torch.ones(2)}),
            write_png(tmp_path / "image.png", np.zeros((4, 4, 3), dtype=np.uint8)),
        ]
        assert default_mode() == 0o666 & ~umask and default_mode(directory=True) == 0o777 & ~umask
    finally:
        os.umask(previous)
    expected = stat.S_IMODE(plain.stat().st_mode)
    assert expected == 0o666 & ~umask
    for path in written:
        assert stat.S_IMODE(path.stat().st_mode) == expected, path.name
    assert torch.equal(load_safetensors(tmp_path / "model.safetensors")["w"], torch.ones(2))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.json", "image.png", "model.safetensors",
                                                           "plain.txt"]


def test_a_folder_copy_is_whole_or_absent_and_replaces_a_killed_ones_leftover(tmp_path):
    source = tmp_path / "run"
    (source / "checkpoints").mkdir(parents=True)
    (source / "model.safetensors").write_bytes(b"weights")
    (source / "checkpoints" / "step_1.safetensors").write_bytes(b"step")
    leftover = tmp_path / ".copy.partial"  # a copy killed half-way
    leftover.mkdir()
    (leftover / "model.safetensors").write_bytes(b"wei")
    (leftover / "stale.txt").write_text("from the killed copy")
    target = atomic_copy_tree(source, tmp_path / "copy")
    assert sorted(p.relative_to(target).as_posix() for p in target.rglob("*")) == [
        "checkpoints", "checkpoints/step_1.safetensors", "model.safetensors"]
    assert (target / "model.safetensors").read_bytes() == b"weights" and not leftover.exists()
    with pytest.raises(FileExistsError, match="copy: exists"):
        atomic_copy_tree(source, target)
