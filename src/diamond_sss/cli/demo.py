"""``diamond-sss demo``: the README's main command, on the embedded demo object."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console
from rich.table import Table


def demo(out: Path = Path("outputs/demo"), data: Path | None = None, views: int = 8, lights: int = 6) -> None:
    """Show the embedded demo capture: a summary table and a views x lights contact sheet PNG.

    Args:
        out: output folder (created; nothing is written elsewhere).
        data: data folder to show instead of the embedded demo object.
        views: rows of the contact sheet (views spread over the lattice).
        lights: columns of the contact sheet (lights spread over the lattice).
    """
    from diamond_sss.data import OLATDataset
    from diamond_sss.data.embedded import embedded_dataset
    from diamond_sss.evaluation.figures import save_image_grid, to_display

    root = data if data is not None else embedded_dataset()
    console = Console()
    table = Table(title=f"DIAMOND-SSS demo data: {root}")
    for column in ("split", "views", "lights", "images", "size"):
        table.add_column(column)
    train = OLATDataset(root, "train")
    splits = [train] + ([OLATDataset(root, "test")] if (root / "transforms_test.json").exists() else [])
    for ds in splits:
        s = ds.summary()
        table.add_row(ds.split, str(s["views"]), str(s["lights"]), str(s["images"]), f"{s['width']}x{s['height']}")
    console.print(table)
    view_ids = [round(i * (train.num_views - 1) / max(1, views - 1)) for i in range(min(views, train.num_views))]
    light_ids = [round(i * (train.num_lights - 1) / max(1, lights - 1)) for i in range(min(lights, train.num_lights))]
    rows = []
    for v in view_ids:
        row = []
        for light in light_ids:
            if bool(train.presence[v, light]):
                row.append(to_display(train.load(train.observation_index(v, light)).rgb))
            else:
                row.append(to_display(train.load(0).rgb * 0))
        rows.append(row)
    sheet = save_image_grid(out / "contact_sheet.png", rows, row_labels=[f"view {v}" for v in view_ids],
                            col_labels=[f"light {light}" for light in light_ids], title=f"{root.name}: views x lights")
    console.print(f"contact sheet: {sheet}")
