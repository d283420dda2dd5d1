"""Dataclass fields that carry their meaning, so a config's default and its help text live in one place."""

from __future__ import annotations

from dataclasses import MISSING, field
from typing import Any


def described(default: Any = MISSING, meaning: str = "", *, factory: Any = MISSING, **metadata: Any) -> Any:
    """A dataclass field with ``default`` (or ``factory``) and its ``meaning`` as ``metadata["help"]``, which
    ``diamond-sss config`` lists and the command line shows as help (:func:`diamond_sss.cli.options.options_of`)."""
    return field(default=default, default_factory=factory, metadata={"help": meaning, **metadata})
