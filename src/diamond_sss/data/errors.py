"""The data layer's error type: every message names the file, and where it applies the frame and the key."""

from __future__ import annotations

from pathlib import Path


class DataError(ValueError):
    """Bad input data: a missing file, a missing or malformed key, an inconsistent capture."""


def data_error(path: Path | str, message: str, *, frame: int | None = None, key: str | None = None) -> DataError:
    """Build a :class:`DataError` reading ``<path>: frame <i>: key '<k>': <message>``."""
    where = [str(path)]
    if frame is not None:
        where.append(f"frame {frame}")
    if key is not None:
        where.append(f"key '{key}'")
    return DataError(": ".join(where + [message]))
