"""Test helpers for the repository's scripts (``benchmarks/*.py``, ``scripts/*.py``), which are not a package."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]


def load_script(relative_path: str, name: str | None = None) -> ModuleType:
    """The module of the script at ``ROOT / relative_path``, executed once under ``name`` (default its stem)."""
    path = ROOT / relative_path
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def assert_stops_naming(parse_args: Callable[[Sequence[str]], object], argv: Sequence[str], message: str,
                        capsys: pytest.CaptureFixture) -> None:
    """``parse_args(argv)`` exits with argparse's usage error (code 2) and ``message`` on stderr."""
    with pytest.raises(SystemExit) as stop:
        parse_args(argv)
    assert stop.value.code == 2 and message in capsys.readouterr().err
