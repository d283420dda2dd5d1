"""``diamond-sss blend-models``: interpolate the weights of two diffusion models of one architecture."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console


def blend_models(first: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="FIRST")],
                 second: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SECOND")],
                 out: Path, weight: float = 0.5) -> None:
    """Write ``(1 - weight) * FIRST + weight * SECOND`` of two model folders (novel-view or relighting, equal
    config.json) to OUT: a model and its fine-tune blended keep more of what each does well (WiSE-FT). The shipped
    novel-view model is the 0.5 blend of the GPU prior and its fine-tune on perturbed reference depth.

    Args:
        first: model folder (weight 1 - WEIGHT).
        second: model folder of the same architecture (weight WEIGHT).
        out: model folder to write (for `nvs --model` / `run --nvs-model`).
        weight: share of SECOND, in [0, 1].
    """
    from diamond_sss.diffusion.common.model_io import blend_model_folders

    folder = blend_model_folders(first, second, weight, out)
    Console().print(f"{1 - weight:g} x {first} + {weight:g} x {second} -> {folder}")
