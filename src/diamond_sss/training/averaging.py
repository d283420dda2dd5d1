"""A uniform average of the scene's tensors over the last steps of a run (Polyak averaging).

Adam's last iterates scatter around the minimum by the step size; their mean ``a_k = a_{k-1} + (p_k - a_{k-1}) / k``
over the final steps removes that scatter (demo object, 10k steps, the last 10%: +0.20 / +0.06 / +0.17 dB test PSNR
on three seeds; at 3k +0.17 / +0.09 dB with the ray-traced-only visibility, on two: so dense short runs of 3k steps or
more average, ``training.config.DENSE_LONG_RUN``; the presets keep the last step's parameters; benchmarks/RESULTS.md,
issue 17). The Gaussian set must keep its size over the
window, so averaging starts after densification stops (:func:`averaging_start`).
"""

from __future__ import annotations

import torch
from torch import Tensor


def averaging_start(iterations: int, average_last: float, densify_stop: int) -> int:
    """First step (0-based) whose result enters the mean: ``max(iterations - round(f iterations), densify_stop)``,
    ``iterations`` (none) for ``f = 0``. ``densify_stop``: the step from which the Gaussian set keeps its size
    (0 when the run does not densify)."""
    if average_last <= 0:
        return iterations
    return max(iterations - round(average_last * iterations), densify_stop)


class ParameterAverage:
    """Running uniform mean of named tensors. Floating-point tensors are averaged; any other tensor is the last
    one given."""

    def __init__(self, mean: dict[str, Tensor] | None = None, count: int = 0) -> None:
        if (mean is None) != (count == 0):
            raise ValueError(f"a ParameterAverage of {count} steps needs {'a' if count else 'no'} mean")
        self.mean = {} if mean is None else {k: v.clone() for k, v in mean.items()}
        self.count = count

    @torch.no_grad()
    def add(self, tensors: dict[str, Tensor]) -> None:
        """Fold one step's tensors into the mean."""
        if self.count:
            if tensors.keys() != self.mean.keys():
                raise ValueError(f"averaged tensors changed names: {sorted(tensors.keys() ^ self.mean.keys())}")
            for name, value in tensors.items():
                if value.shape != self.mean[name].shape:
                    raise ValueError(f"averaged tensor '{name}' changed shape: {tuple(self.mean[name].shape)} -> "
                                     f"{tuple(value.shape)} (did the Gaussian set change inside the window?)")
        self.count += 1
        for name, value in tensors.items():
            if self.count == 1 or not value.is_floating_point():
                self.mean[name] = value.detach().clone()
            else:
                self.mean[name].lerp_(value.detach(), 1.0 / self.count)
