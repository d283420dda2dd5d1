"""``diamond-sss demo``: the README's main command, on the embedded demo object (wax bunny, 64x64)."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console
from rich.table import Table


def demo(out: Path = Path("outputs/demo"), data: Path | None = None, regime: str = "views=3,lights=3",
         iterations: int = 1000, augment: str = "auto", dense: bool = True, parallel: bool = True,
         quiet: bool = False) -> None:
    """SSS-3DGS vs DIAMOND-SSS on a sparse capture of the embedded demo object (9 images), on a CPU budget.

    Runs (each resumable under --out; a run made with other models or settings is moved aside to
    <name>.<hash>): SSS-3DGS (`sss3dgs` preset) on the regime's real images only; the DIAMOND-SSS
    pipeline (the SSS-3DGS run reused as its preliminary reconstruction, the augmentation of --augment with the
    shipped models, final reconstruction); with --dense, DIAMOND-SSS on every image as the
    dense reference.
    Prints the metrics on novel views under novel lights and writes report.md and comparison.png.

    Args:
        out: output folder.
        data: data folder to use instead of the embedded demo object (needs a test split).
        regime: sparse capture regime (default: 3 views x 3 lights = 9 images).
        iterations: training steps of every reconstruction.
        augment: augmentation: auto (render repair when its model ships with the package, else the paper's stages
            whose model ships; `diamond-sss run` says why) | none | nvs | relight | nvs,relight | repair.
        dense: also reconstruct from all images (the upper reference).
        parallel: train the dense reconstruction in a second process beside the other two (on 2+ cores; each
            run trains on one thread either way, so the numbers are the same).
        quiet: no progress bars.
    """
    from diamond_sss.experiments.demo import COLUMNS, run_demo

    console = Console()
    result = run_demo(out, data, regime=regime, iterations=iterations, augment=augment, dense=dense,
                      parallel=parallel, show_progress=not quiet)
    for folder in result.moved:
        console.print(f"a run made with other settings was moved aside to {folder}")
    table = Table(title=result.title, caption="SSS-3DGS: real images only; DIAMOND-SSS: the full pipeline; "
                  "dense: all images")
    for column in COLUMNS:
        table.add_column(column, no_wrap=column == "method")
    for row in result.rows:
        table.add_row(row.label.split(" (")[0], *row.cells())
    console.print(table)
    console.print(f"report: {result.report}\nfigure: {result.figure}")
