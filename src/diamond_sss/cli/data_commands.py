"""``diamond-sss info``, ``regimes`` and ``subset``: inspect a data set and a capture regime, export a regime."""

from __future__ import annotations

import json as json_module
from pathlib import Path

from rich.console import Console
from rich.table import Table


def info(data: Path, split: str = "train", json: bool = False, downscale: float = 1.0) -> None:
    """Summarise an OLAT data set: views, lights, images, image size, scene bounds.

    Args:
        data: data folder holding transforms_<split>.json.
        split: which transforms_<split>.json to read (train, test, or any other).
        json: print a JSON object instead of a table.
        downscale: report sizes after dividing the image size by this factor.
    """
    from diamond_sss.data import OLATDataset

    summary = OLATDataset(data, split, downscale=downscale).summary()
    if json:
        print(json_module.dumps(summary, indent=2))
        return
    table = Table(title=f"{data} [{split}]", show_header=False)
    for key, value in summary.items():
        table.add_row(key, format_bounds(value) if key == "bounds" else str(value))
    Console().print(table)


def format_bounds(bounds: dict) -> str:
    """Scene bounds as text: ``center (x, y, z), radius r, near n, far f`` (4 significant digits)."""
    center = ", ".join(f"{x + 0.0:.4g}" for x in bounds["center"])
    return (f"center ({center}), radius {bounds['radius']:.4g}, near {bounds['near']:.4g}, "
            f"far {bounds['far']:.4g}")


def regimes(data: Path, regime: str = "all", split: str = "train", seed: int = 0, json: bool = False) -> None:
    """Show which views, lights and images a capture regime selects (deterministic under --seed).

    Args:
        data: data folder holding transforms_<split>.json.
        regime: all | all-views-1-light | views=5%,lights=5% | views=5,lights=6 | images=10.
        split: which transforms_<split>.json to select from.
        seed: seed of the farthest-point sampling's first pick.
        json: print a JSON object (views, lights, observations, images).
    """
    from diamond_sss.data import OLATDataset, select_regime

    dataset = OLATDataset(data, split)
    selection = select_regime(dataset, regime, seed)
    if json:
        print(json_module.dumps(selection.to_json()))
        return
    table = Table(title=f"regime '{regime}' (seed {seed}) on {data} [{split}]", show_header=False)
    table.add_row("views", f"{len(selection.views)} of {dataset.num_views}: {selection.views}")
    table.add_row("lights", f"{len(selection.lights)} of {dataset.num_lights}: {selection.lights}")
    table.add_row("images", f"{len(selection.observations)} of {len(dataset)}")
    if selection.note:
        table.add_row("note", selection.note)
    Console().print(table)


def subset(data: Path, out: Path, regime: str, split: str = "train", seed: int = 0) -> None:
    """Write a capture holding only the images a regime selects, as a user's own sparse capture looks.

    OUT gets transforms_<split>.json listing just those images (copied, with their masks and depth / normal maps),
    the whole transforms_test.json with its images (so the export can be evaluated) and subset.json (source, regime,
    selection). Built in a temporary folder and renamed into place; OUT must not exist.

    Args:
        data: data folder holding transforms_<split>.json.
        out: folder to create.
        regime: all-views-1-light | views=5%,lights=5% | views=5,lights=6 | images=10 (see `diamond-sss regimes`).
        split: which transforms_<split>.json to select from.
        seed: seed of the farthest-point sampling's first pick.
    """
    from diamond_sss.data.export import export_regime

    result = export_regime(data, out, regime, split=split, seed=seed)
    counts = ", ".join(f"{count} {name} images" for name, count in result.images.items())
    print(f"{result.out}: {counts} (regime '{regime}', seed {seed}, views {result.selection.views}, "
          f"lights {result.selection.lights})")
    for note in (result.selection.note, result.note):
        if note:
            print(note)
