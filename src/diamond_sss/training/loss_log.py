"""Loss terms kept on the training device until they are read (no host-device sync per step)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor


class LossLog:
    """Loss terms of recent steps, kept on the training device until they are read.

    Reading a loss (``float(tensor)``) makes the host wait for the device; recording the terms and reading
    them all at once (:meth:`flush`, one transfer) keeps the training step free of synchronisation.
    """

    def __init__(self) -> None:
        self._pending: list[tuple[int, tuple[str, ...], Tensor]] = []

    def record(self, step: int, terms: Mapping[str, Tensor]) -> None:
        """Keep the (scalar) terms of ``step``."""
        names = tuple(terms)
        if names:
            self._pending.append((step, names, torch.stack([terms[n].detach().float() for n in names])))

    def flush(self) -> dict[str, float]:
        """The terms of the last recorded step as floats; clears the log.

        Raises:
            FloatingPointError: at the first recorded step with a non-finite term, naming the step and terms.
        """
        if not self._pending:
            return {}
        pending, self._pending = self._pending, []
        values = torch.cat([row for _, _, row in pending]).cpu().tolist()
        offset = 0
        for step, names, _ in pending:
            terms = dict(zip(names, values[offset: offset + len(names)]))
            offset += len(names)
            bad = [name for name, value in terms.items() if not math.isfinite(value)]
            if bad:
                raise FloatingPointError(
                    f"non-finite loss at step {step}: {', '.join(bad)} (terms {terms}); the run stops here and "
                    "keeps its last checkpoint (check the learning rates and loss weights)")
        return terms
