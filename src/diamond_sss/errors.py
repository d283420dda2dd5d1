"""Errors of bad input (data sets, run folders, weights): every message names the file, and where it applies
the frame and the key. Free of heavy imports: the CLI catches these before anything else is loaded.
"""

from __future__ import annotations

from pathlib import Path


class DataError(ValueError):
    """Bad input data: a missing file, a missing or malformed key, an inconsistent capture."""


class DamagedFileError(DataError):
    """A file that exists but cannot be parsed (truncated safetensors, corrupt JSON)."""


def data_error(path: Path | str, message: str, *, frame: int | None = None, key: str | None = None) -> DataError:
    """Build a :class:`DataError` reading ``<path>: frame <i>: key '<k>': <message>``."""
    where = [str(path)]
    if frame is not None:
        where.append(f"frame {frame}")
    if key is not None:
        where.append(f"key '{key}'")
    return DataError(": ".join(where + [message]))
