"""Atomic file writes and content hashes (caches are keyed by content and written atomically)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from diamond_sss.errors import DamagedFileError, DataError


def default_mode(directory: bool = False) -> int:
    """The mode a plain ``open(path, "w")`` (``0o666``) or ``mkdir`` (``0o777``) gives, less the umask."""
    umask = os.umask(0)
    os.umask(umask)
    return (0o777 if directory else 0o666) & ~umask


def atomic_write(path: str | os.PathLike, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp_path)`` on a temporary file beside ``path``, then ``os.replace`` it into place.

    A crash leaves either the old file or the new one, never half of it. Parent folders are created. The
    file gets the mode a plain write would give it (not ``mkstemp``'s 0600).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        write(tmp_path)
        os.chmod(tmp_path, default_mode())
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()
    return path


def atomic_copy_tree(source: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Copy the folder ``source`` to ``target`` (which must not exist) through a temporary folder beside it, renamed
    into place: a crash leaves no ``target`` or a whole one (a leftover temporary folder is replaced next time)."""
    target = Path(target)
    if target.exists():
        raise FileExistsError(f"{target}: exists; the copy of {source} would replace it")
    partial = target.with_name(f".{target.name}.partial")
    if partial.exists():
        shutil.rmtree(partial)
    shutil.copytree(source, partial)
    os.replace(partial, target)
    return target


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return atomic_write(path, lambda tmp: tmp.write_bytes(data))


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def atomic_save_safetensors(path: str | os.PathLike, tensors: dict[str, torch.Tensor],
                            metadata: dict[str, str] | None = None) -> Path:
    """Save tensors (moved to CPU, made contiguous) to a safetensors file atomically.

    The written file is re-opened (header and sizes parsed, keys compared) before it replaces ``path``.
    """
    cpu = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}

    def write(tmp: Path) -> None:
        save_file(cpu, str(tmp), metadata=metadata)
        verify_safetensors(tmp, set(cpu), name=Path(path))

    return atomic_write(path, write)


def verify_safetensors(path: str | os.PathLike, keys: set[str], name: str | os.PathLike | None = None) -> None:
    """Raise :class:`DamagedFileError` unless ``path`` opens as safetensors holding exactly ``keys``."""
    try:
        with safe_open(str(path), framework="pt") as handle:
            found = set(handle.keys())
    except (SafetensorError, OSError) as exc:
        raise DamagedFileError(f"{name or path}: written safetensors file does not read back ({exc})") from exc
    if found != keys:
        raise DamagedFileError(f"{name or path}: written safetensors file holds keys {sorted(found)}, "
                               f"expected {sorted(keys)}")


def load_safetensors(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """Load a safetensors file to CPU tensors (never a pickle); a damaged file raises naming it."""
    if not Path(path).is_file():
        raise DataError(f"{path}: file is missing")
    try:
        return load_file(str(path), device="cpu")
    except (SafetensorError, OSError) as exc:
        raise DamagedFileError(f"{path}: damaged or truncated safetensors file ({exc})") from exc


def read_json(path: str | os.PathLike) -> Any:
    """Parse a JSON file; a missing or corrupt file raises a :class:`DataError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: file is missing")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DamagedFileError(f"{path}: damaged or invalid JSON ({exc})") from exc


def move_aside(folder: Path, tag: str) -> Path:
    """Rename ``folder`` to ``<folder>.<tag>`` (``-2``, ``-3``, ... if taken) and return the new path; nothing is
    deleted. Used for run folders made with other inputs than a job now asks for."""
    folder = Path(folder)
    target = folder.with_name(f"{folder.name}.{tag}")
    suffix = 2
    while target.exists():
        target = folder.with_name(f"{folder.name}.{tag}-{suffix}")
        suffix += 1
    folder.rename(target)
    return target


def sha256_bytes(data: bytes) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike, chunk_size: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's content."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(chunk_size), b""):
            digest.update(chunk)
    return digest.hexdigest()


def sha256_json(obj: Any) -> str:
    """Hex SHA-256 of the canonical JSON form of ``obj`` (sorted keys)."""
    return sha256_bytes(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode("utf-8"))
