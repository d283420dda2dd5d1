"""Where the steps of a training loop spend their time: dispatched operators, CUDA kernels and host syncs."""

from __future__ import annotations

import collections
import json
import warnings
from collections.abc import Callable
from pathlib import Path

import torch


def synchronize(device: torch.device) -> None:
    """Wait for the work queued on ``device`` (a no-op off CUDA), so that wall clocks time the work itself."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def profile_steps(step: Callable[[int], object], device: torch.device, first: int, steps: int, path: Path) -> dict:
    """Profile ``step(i)`` for ``i`` in ``[first, first + steps)``: torch.profiler's operators by self CPU time (on
    CUDA also by self CUDA time and the kernels launched), and on CUDA every host sync with its call site
    (``torch.cuda.set_sync_debug_mode("warn")``: a sync stops the host from queueing ahead of the GPU). Writes the
    tables to ``path`` (its folder made if missing); returns ``operators_per_step``, ``cuda_kernels_per_step`` and ``host_syncs_per_step``."""
    from torch.profiler import ProfilerActivity, profile

    cuda = device.type == "cuda"
    activities = [ProfilerActivity.CPU, *([ProfilerActivity.CUDA] if cuda else [])]
    syncs: collections.Counter[str] = collections.Counter()
    with profile(activities=activities) as prof, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if cuda:
            torch.cuda.set_sync_debug_mode("warn")
        try:
            for i in range(first, first + steps):
                step(i)
            synchronize(device)
        finally:
            if cuda:
                torch.cuda.set_sync_debug_mode("default")
    for warning in caught:
        if "synchroniz" in str(warning.message):
            syncs[f"{Path(warning.filename).name}:{warning.lineno}"] += 1
    events = prof.events()
    operators = sum(1 for e in events if e.name.startswith("aten::") and not _nested(e))
    kernels = sum(1 for e in events if e.device_type == torch.autograd.DeviceType.CUDA)
    counts = {"operators_per_step": operators / steps, "cuda_kernels_per_step": kernels / steps,
              "host_syncs_per_step": sum(syncs.values()) / steps}
    averages = prof.key_averages()
    sections = [json.dumps(counts), "", "Host syncs (call site: count over the steps):",
                *(f"  {site}: {n}" for site, n in syncs.most_common()), "",
                averages.table(sort_by="self_cpu_time_total", row_limit=30)]
    if cuda:
        sections.append(averages.table(sort_by="self_cuda_time_total", row_limit=30))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(sections) + "\n")
    return counts


def _nested(event) -> bool:
    """Whether a profiler event runs inside another operator (only top-level operators are dispatches)."""
    parent = event.cpu_parent
    while parent is not None:
        if parent.name.startswith("aten::"):
            return True
        parent = parent.cpu_parent
    return False
