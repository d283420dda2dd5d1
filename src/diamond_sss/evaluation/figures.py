"""Figures: image grids with labels (contact sheets, GT | render | error panels)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from torch import Tensor

from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.utils.io import atomic_write


def to_display(image: Tensor, *, linear: bool = True) -> np.ndarray:
    """``[H,W,C]`` tensor -> float ``[H,W,3]`` display array in [0,1] (sRGB-encoded when ``linear``)."""
    image = image.detach().float().cpu()
    if image.shape[-1] == 1:
        image = image.expand(*image.shape[:-1], 3)
    image = linear_to_srgb(image) if linear else image.clamp(0.0, 1.0)
    return image.numpy()


def save_image_grid(path: str | os.PathLike, rows: Sequence[Sequence[np.ndarray]], *,
                    row_labels: Sequence[str] | None = None, col_labels: Sequence[str] | None = None,
                    cell_labels: Sequence[Sequence[str]] | None = None, title: str | None = None,
                    cell_inches: float = 1.4) -> Path:
    """Save a grid of display images (``[H,W,3]`` floats in [0,1]) as a PNG.

    Labels: ``col_labels`` above the first row, ``row_labels`` left of each row, or ``cell_labels`` (one per
    image) above every image.
    """
    num_rows = len(rows)
    num_cols = max(len(r) for r in rows)
    fig, axes = plt.subplots(num_rows, num_cols, figsize=(cell_inches * num_cols, cell_inches * num_rows + 0.4),
                             squeeze=False)
    for r in range(num_rows):
        for c in range(num_cols):
            ax = axes[r][c]
            ax.set_xticks([])
            ax.set_yticks([])
            for spine in ax.spines.values():
                spine.set_visible(False)
            if c < len(rows[r]):
                ax.imshow(rows[r][c], interpolation="nearest")
            if cell_labels is not None and c < len(cell_labels[r]):
                ax.set_title(cell_labels[r][c], fontsize=7)
            elif col_labels is not None and r == 0 and c < len(col_labels):
                ax.set_title(col_labels[c], fontsize=7)
            if row_labels is not None and c == 0 and r < len(row_labels):
                ax.set_ylabel(row_labels[r], fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    written = atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    plt.close(fig)
    return written
