"""The fine-tuning runtime: one place that makes the ``Accelerator`` and the optimiser, scopes deterministic kernels
and keeps a run's wall-time limit."""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import time
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, ParamSpec, TypeVar

import torch
from accelerate import Accelerator
from accelerate.state import AcceleratorState

from diamond_sss.errors import DamagedFileError
from diamond_sss.utils.io import read_json

P = ParamSpec("P")
R = TypeVar("R")


@contextlib.contextmanager
def kernel_settings(deterministic: bool) -> Iterator[None]:
    """cuDNN and torch's kernel choice for the block, restored after: ``deterministic`` (cuDNN's deterministic
    convolution algorithms without autotuning, cuBLAS with a fixed workspace, ``CUBLAS_WORKSPACE_CONFIG=:4096:8``
    unless set, and an operation without a deterministic CUDA kernel raises: ``warn_only=True`` would let the
    memory-efficient attention keep its non-deterministic backward, which made two seeded novel-view fine-tunes on
    an H200 differ in 84 of 259 tensors, 2026-11-28) or autotuned (cuDNN benchmarks its algorithms, no
    deterministic algorithms asked for)."""
    if deterministic:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    previous = (torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark,
                torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled())
    torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = deterministic, not deterministic
    torch.use_deterministic_algorithms(deterministic, warn_only=False)
    try:
        yield
    finally:
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = previous[:2]
        torch.use_deterministic_algorithms(previous[2], warn_only=previous[3])


def deterministic_kernels(fn: Callable[P, R]) -> Callable[P, R]:
    """Run ``fn`` under ``kernel_settings(deterministic=True)``, so a seeded fine-tune (and its resume) is
    reproducible on CUDA. Costs a few percent of speed on CUDA; CPU results do not change."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with kernel_settings(deterministic=True):
            return fn(*args, **kwargs)

    return wrapper


MIXED_PRECISIONS = ("no", "fp16", "bf16")
"""accelerate's autocast settings: none, float16 (CUDA only) and bfloat16."""


def fused_adamw(parameters: Iterable[torch.nn.Parameter], learning_rate: float, weight_decay: float) -> torch.optim.AdamW:
    """AdamW in torch's fused kernel (CPU and CUDA, torch >= 2.4): a step is a few kernels instead of a dozen operators
    per tensor (the 6.4 M-parameter, 614-tensor prior: 56 -> 22 ms on one CPU thread); the same update rule."""
    return torch.optim.AdamW(parameters, lr=learning_rate, weight_decay=weight_decay, fused=True)


def make_accelerator(mixed_precision: str = "no") -> Accelerator:
    """An ``Accelerator`` on CUDA when available (else CPU) with ``mixed_precision`` (``no``/``fp16``/``bf16``).

    accelerate keeps one process-wide state and refuses a second ``Accelerator`` with another device or
    precision; fine-tunes run one after another in one process (the pipeline, the test suite), so a state
    left by an earlier one with other settings is cleared first. ``fp16`` without CUDA is refused (accelerate
    would silently train in float32).
    """
    cpu = not torch.cuda.is_available()
    if mixed_precision not in MIXED_PRECISIONS:
        raise ValueError(f"mixed_precision must be one of {MIXED_PRECISIONS}, got {mixed_precision!r}")
    if cpu and mixed_precision == "fp16":
        raise ValueError("mixed_precision 'fp16' needs a CUDA GPU (none is visible); use 'bf16' or 'no' on the CPU")
    state = AcceleratorState._shared_state
    if state and (state.get("_mixed_precision") != mixed_precision
                  or (cpu and getattr(state.get("device"), "type", "cpu") != "cpu")):
        AcceleratorState._reset_state(reset_partial_state=True)
    return Accelerator(mixed_precision=mixed_precision, cpu=cpu)


class Deadline:
    """The wall-time limit of a fine-tuning loop (``time_limit_s``, seconds; ``None``: none), counted from its
    creation."""

    def __init__(self, seconds: float | None) -> None:
        if seconds is not None and not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"time_limit_s must be a finite number of seconds >= 0 or None, got {seconds}")
        self.seconds = seconds
        self.started = time.perf_counter()

    def elapsed(self) -> float:
        """Seconds since the loop started."""
        return time.perf_counter() - self.started

    def passed(self) -> bool:
        """Whether the limit is spent (never without one)."""
        return self.seconds is not None and self.elapsed() > self.seconds


_MISSING = object()


def check_resumed_settings(path: str | os.PathLike, settings: dict, may_change: Collection[str],
                           implied: Mapping[str, Any] | None = None) -> None:
    """Refuse to resume a fine-tune whose settings, as recorded in ``path`` (JSON) when it started, differ from
    ``settings`` in any key but the top-level ``may_change`` ones (those that a resumed run may change without
    making it another run: its length, how often it logs and checkpoints): a ``ValueError`` naming each differing
    dotted key, ``recorded -> given``. ``implied``: top-level keys added since older records were written, with the
    value such a record stands for (what the code that wrote it did)."""
    path = Path(path)
    recorded = read_json(path)
    if not isinstance(recorded, dict):
        raise DamagedFileError(f"{path}: expected a JSON object of fine-tuning settings, got {type(recorded).__name__}")
    recorded = {**(implied or {}), **recorded}
    given = json.loads(json.dumps(settings))  # as the record holds them (tuples read back as lists)
    old, new = _dotted(recorded), _dotted(given)
    changed = [f"{key}: {_shown(old, key)} -> {_shown(new, key)}" for key in sorted(old.keys() | new.keys())
               if key.split(".")[0] not in may_change and old.get(key, _MISSING) != new.get(key, _MISSING)]
    if changed:
        raise ValueError(f"{path}: the checkpoints in {path.parent} belong to a fine-tune with other settings "
                         f"({'; '.join(changed)}); resuming would mix two runs: give the recorded settings (only "
                         f"{', '.join(sorted(may_change))} may change), or fine-tune into another --out")


def _dotted(value: Any, prefix: str = "") -> dict[str, Any]:
    """Leaves of nested dicts by dotted key (a non-dict value is a leaf)."""
    if not isinstance(value, dict):
        return {prefix: value}
    flat: dict[str, Any] = {}
    for key, item in value.items():
        flat.update(_dotted(item, f"{prefix}.{key}" if prefix else str(key)))
    return flat


def _shown(values: dict[str, Any], key: str) -> str:
    return repr(values[key]) if key in values else "missing"
