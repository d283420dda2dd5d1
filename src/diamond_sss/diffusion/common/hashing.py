"""Content hashes of models, used as cache keys (a changed weight or config invalidates cached outputs)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import torch
from torch import Tensor

from diamond_sss.utils.io import sha256_file


def state_dict_hash(state: dict[str, Tensor]) -> str:
    """Hex SHA-256 over the sorted names, dtypes, shapes and bytes of a state dict's tensors."""
    digest = hashlib.sha256()
    for key in sorted(state):
        tensor = state[key].detach().cpu().contiguous()
        digest.update(f"{key}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        # flat first: a contiguous tensor with a size-1 dimension may keep any stride there, which .view refuses
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return digest.hexdigest()


def files_hash(root: str | os.PathLike, suffixes: tuple[str, ...] = (".json", ".safetensors", ".bin")) -> str:
    """Hex SHA-256 of every file under ``root`` whose name ends with one of ``suffixes`` (path + content)."""
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"cannot hash {root}: it does not exist")
    files = (
        [root]
        if root.is_file()
        else sorted(p for p in root.rglob("*") if p.is_file() and p.suffix in suffixes)
    )
    digest = hashlib.sha256()
    for path in files:
        digest.update(
            f"{path.relative_to(root) if path != root else path.name}|{sha256_file(path)}|".encode()
        )
    return digest.hexdigest()
