"""The torch device a configuration names."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


def resolve_device(name: str) -> torch.device:
    """``auto`` -> CUDA when available, else CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"device '{name}': expected auto | cpu | cuda[:i]") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("config 'device' asks for CUDA but torch.cuda.is_available() is False")
    return device


def to_device(tensor: torch.Tensor, device: torch.device | str) -> torch.Tensor:
    """``tensor`` on ``device``; a host tensor goes to CUDA through pinned memory without blocking the host (a copy
    from pageable memory first waits for everything queued on the GPU), so that the host goes on queueing kernels."""
    device = torch.device(device)
    if device.type == "cuda" and tensor.device.type == "cpu":
        return tensor.pin_memory().to(device, non_blocking=True)
    return tensor.to(device)


@contextmanager
def cpu_threads(count: int) -> Iterator[None]:
    """torch's intra-op CPU threads set to ``count`` inside the block and restored after it (``count`` <= 0: left as
    they are), so that one job's setting does not stay with the process (e.g. a trainer's 1 thread with the diffusion
    stages that follow it)."""
    before = torch.get_num_threads()
    if count > 0:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)
