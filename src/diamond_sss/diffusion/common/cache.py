"""Content-keyed on-disk cache of generated outputs: one folder per key, published atomically."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from diamond_sss.utils.io import sha256_json

ENTRY_FORMAT = 2
"""How an entry's files are encoded, hashed into every key so that a change never reuses older entries
(2: RGBA files hold no colour where their alpha is 0, :func:`diamond_sss.data.images.to_srgb8`)."""


class OutputCache:
    """Folders ``<root>/<key[:2]>/<key>`` holding the files generated for a key.

    ``key(parts)`` hashes any JSON-able description of the inputs (model hash, input hashes, settings).
    ``put`` writes into a temporary folder beside the target and renames it into place, so a reader sees
    either nothing or a complete entry; a concurrent writer of the same key loses the race harmlessly.
    """

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)

    @staticmethod
    def key(parts: Any) -> str:
        """Hex SHA-256 of the canonical JSON of ``parts`` and :data:`ENTRY_FORMAT`."""
        return sha256_json({"entry_format": ENTRY_FORMAT, "inputs": parts})

    def path(self, key: str) -> Path:
        return self.root / key[:2] / key

    def get(self, key: str) -> Path | None:
        """Folder of a complete entry, or ``None`` on a miss."""
        path = self.path(key)
        return path if path.is_dir() else None

    def put(self, key: str, write: Callable[[Path], None]) -> Path:
        """Call ``write(folder)`` on an empty temporary folder, then publish it as the entry of ``key``."""
        final = self.path(key)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key[:8]}.", suffix=".tmp", dir=final.parent))
        try:
            write(tmp)
            try:
                os.replace(tmp, final)
            except OSError:
                if not final.is_dir():
                    raise
        finally:
            if tmp.exists():
                shutil.rmtree(tmp)
        return final

    def get_or_create(self, key: str, write: Callable[[Path], None]) -> tuple[Path, bool]:
        """``(folder, hit)``: the cached entry, generating it with ``write`` on a miss."""
        hit = self.get(key)
        if hit is not None:
            return hit, True
        return self.put(key, write), False
