"""``torch.compile`` as a setting (``runtime.compile``): what is compiled and with which backend.

On CUDA a training step is host-bound: its elementwise work (per-Gaussian features, deferred shading, the image
objective) is ~2,000 small kernels launched one by one. Compiling fuses them (forward and backward). What is
compiled are pure functions between the rasterizer calls (gsplat's kernels and the CPU tiler stay eager: their
shapes depend on the data): :meth:`~diamond_sss.scene.model.RelightableScene.compile_shading` and the trainer's image
objective and multi-view losses. Measured on an H100 (benchmarks/RESULTS.md, session 46): 1,913 -> 316 operators and
19.9 -> 8.4 ms per step at 10k Gaussians and 64 px; 25.4 -> 16.9 ms at 300k and 800 px.
"""

from __future__ import annotations

import importlib.util
import shutil
import warnings
from collections.abc import Callable
from typing import TypeVar

import torch

COMPILE_BACKENDS = ("off", "inductor", "aot_eager")
"""``off``: eager PyTorch; ``inductor``: fused kernels (Triton on CUDA, C++ on CPU: needs a compiler);
``aot_eager``: the same graphs run by eager kernels (no code generation: checks that a function traces)."""

F = TypeVar("F", bound=Callable)


def compiled(fn: F, backend: str) -> F:
    """``fn`` compiled with ``backend`` (one of :data:`COMPILE_BACKENDS`), or ``fn`` itself for ``off``. Shapes
    that change (the Gaussian count under densification) recompile once as dynamic, then stay."""
    if backend not in COMPILE_BACKENDS:
        raise ValueError(f"compile backend must be one of {COMPILE_BACKENDS}, got {backend!r}")
    if backend == "off":
        return fn
    # Dynamo traces through functools.lru_cache wrappers (the SSIM window, pixel grids): pure functions, so the
    # values are the same; its warning about it would repeat in every run's log.
    warnings.filterwarnings("ignore", message="Dynamo detected a call to a `functools.lru_cache`")
    # Densification replaces the Gaussians' parameters by longer ones: with static parameter shapes (dynamo's
    # default) every new count would compile again, up to its cache limit, then run eagerly.
    torch._dynamo.config.force_parameter_static_shapes = False
    return torch.compile(fn, backend=backend)


def compile_unavailable(backend: str, device: torch.device) -> str | None:
    """Why ``backend`` cannot compile for ``device`` here (``None``: it can): inductor needs triton on CUDA and a C++
    compiler on the CPU; ``off`` and ``aot_eager`` need neither."""
    if backend != "inductor":
        return None
    if device.type == "cuda" and importlib.util.find_spec("triton") is None:
        return "inductor on CUDA needs triton (CUDA builds of torch install it), which is not installed"
    if device.type == "cpu" and not any(shutil.which(name) for name in ("c++", "g++", "clang++")):
        return "inductor on the CPU needs a C++ compiler (c++, g++ or clang++ on PATH), and none was found"
    return None
