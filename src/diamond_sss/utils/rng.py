"""Seeded random streams, device-agnostic by construction.

Every random draw of the project goes through these helpers, so a generator and the tensor it fills can
never disagree on the device (torch refuses a CPU generator for a CUDA draw and vice versa). A draw is
made on the generator's own device and the result is moved to the device of the data it meets; with
``generator=None`` it is made directly on ``device`` from torch's global stream.

Two kinds of stream serve a training step:

* host streams (:func:`stream_generator` with ``device="cpu"``) for decisions taken in Python (which
  images, which view pairs): drawing them never waits for the GPU;
* device streams (``device=`` the training device) for tensors that live there (sampled directions,
  Gaussian subsets): no host-to-device copy, no synchronisation.

A stream is a pure function of ``(seed, step, stream)``, so a resumed run draws what an uninterrupted
one draws. CPU and CUDA streams of the same seed differ (different generators); each is deterministic.
"""

from __future__ import annotations

import torch
from torch import Tensor

DeviceLike = torch.device | str


def stream_seed(seed: int, step: int, stream: int) -> int:
    """The seed of random stream ``stream`` (``0..15``) of step ``step``: ``(seed 1000003 + step) 16 + stream``."""
    if not 0 <= stream < 16:
        raise ValueError(f"stream must be in 0..15, got {stream}")
    return (seed * 1_000_003 + step) * 16 + stream


def stream_generator(seed: int, step: int, stream: int, device: DeviceLike = "cpu") -> torch.Generator:
    """A generator on ``device`` seeded for stream ``stream`` of step ``step`` (see :func:`stream_seed`)."""
    return torch.Generator(device=torch.device(device)).manual_seed(stream_seed(seed, step, stream))


def _draw_device(generator: torch.Generator | None, device: DeviceLike | None) -> torch.device:
    if generator is not None:
        return generator.device
    return torch.device("cpu") if device is None else torch.device(device)


def _target_device(generator: torch.Generator | None, device: DeviceLike | None) -> torch.device:
    if device is not None:
        return torch.device(device)
    return torch.device("cpu") if generator is None else generator.device


def randn(*shape: int, generator: torch.Generator | None = None, device: DeviceLike | None = None,
          dtype: torch.dtype = torch.float32) -> Tensor:
    """Standard normal samples of ``shape`` on ``device`` (default: the generator's device)."""
    draw = torch.randn(*shape, generator=generator, device=_draw_device(generator, device), dtype=dtype)
    return draw.to(_target_device(generator, device))


def rand(*shape: int, generator: torch.Generator | None = None, device: DeviceLike | None = None,
         dtype: torch.dtype = torch.float32) -> Tensor:
    """Uniform samples in ``[0, 1)`` of ``shape`` on ``device`` (default: the generator's device)."""
    draw = torch.rand(*shape, generator=generator, device=_draw_device(generator, device), dtype=dtype)
    return draw.to(_target_device(generator, device))


def randperm(n: int, *, generator: torch.Generator | None = None, device: DeviceLike | None = None) -> Tensor:
    """A random permutation of ``0..n-1`` (int64) on ``device`` (default: the generator's device)."""
    draw = torch.randperm(n, generator=generator, device=_draw_device(generator, device))
    return draw.to(_target_device(generator, device))


def randint(high: int, *shape: int, generator: torch.Generator | None = None,
            device: DeviceLike | None = None) -> Tensor:
    """Integers uniform in ``[0, high)`` (int64) of ``shape`` on ``device`` (default: the generator's)."""
    draw = torch.randint(high, shape, generator=generator, device=_draw_device(generator, device))
    return draw.to(_target_device(generator, device))
