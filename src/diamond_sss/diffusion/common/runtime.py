"""The fine-tuning runtime: one place that makes the ``Accelerator`` and scopes deterministic kernels."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import ParamSpec, TypeVar

import torch
from accelerate import Accelerator
from accelerate.state import AcceleratorState

P = ParamSpec("P")
R = TypeVar("R")


def deterministic_kernels(fn: Callable[P, R]) -> Callable[P, R]:
    """Run ``fn`` with deterministic kernels, so a seeded fine-tune (and its resume) is reproducible on CUDA.

    cuDNN picks deterministic convolution algorithms (no autotuning), cuBLAS gets a fixed workspace
    (``CUBLAS_WORKSPACE_CONFIG=:4096:8`` unless set; read when its first handle is made), and operations
    without a deterministic CUDA kernel warn instead of failing. The previous settings are restored after.
    Costs a few percent of speed on CUDA; CPU results do not change.
    """

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        previous = (torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark,
                    torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled())
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
        torch.use_deterministic_algorithms(True, warn_only=True)
        try:
            return fn(*args, **kwargs)
        finally:
            torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = previous[:2]
            torch.use_deterministic_algorithms(previous[2], warn_only=previous[3])

    return wrapper


def make_accelerator(mixed_precision: str = "no") -> Accelerator:
    """An ``Accelerator`` on CUDA when available (else CPU) with ``mixed_precision`` (``no``/``fp16``/``bf16``).

    accelerate keeps one process-wide state and refuses a second ``Accelerator`` with another device or
    precision; fine-tunes run one after another in one process (the pipeline, the test suite), so a state
    left by an earlier one with other settings is cleared first.
    """
    cpu = not torch.cuda.is_available()
    state = AcceleratorState._shared_state
    if state and (state.get("_mixed_precision") != mixed_precision
                  or (cpu and getattr(state.get("device"), "type", "cpu") != "cpu")):
        AcceleratorState._reset_state(reset_partial_state=True)
    return Accelerator(mixed_precision=mixed_precision, cpu=cpu)
