"""``diamond-sss demo``: the README's main command, on the embedded demo object (wax bunny, 64x64)."""

from __future__ import annotations

import json
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table


def demo(out: Path = Path("outputs/demo"), data: Path | None = None, regime: str = "views=3,lights=3",
         iterations: int = 1000, augment: str = "auto", dense: bool = True, quiet: bool = False) -> None:
    """SSS-3DGS vs DIAMOND-SSS on a sparse capture of the embedded demo object (9 images), on a CPU budget.

    Runs (each resumable under --out; a DIAMOND-SSS run made with other models or settings is moved aside to
    diamond.<hash>): SSS-3DGS (`sss3dgs` preset) on the regime's real images only; the DIAMOND-SSS
    pipeline (the SSS-3DGS run reused as its preliminary reconstruction, novel-view and relighting diffusion
    with the shipped models, final reconstruction with multi-view losses); with --dense, DIAMOND-SSS on every
    image as the dense reference.
    Prints the metrics on novel views under novel lights and writes report.md and comparison.png.

    Args:
        out: output folder.
        data: data folder to use instead of the embedded demo object (needs a test split).
        regime: sparse capture regime (default: 3 views x 3 lights = 9 images).
        iterations: training steps of every reconstruction.
        augment: diffusion stages: auto (those whose model ships with the package) | none | nvs | relight |
            nvs,relight.
        dense: also reconstruct from all images (the upper reference).
        quiet: no progress bars.
    """
    from diamond_sss.data.dataset import OLATDataset
    from diamond_sss.data.embedded import embedded_dataset
    from diamond_sss.evaluation.evaluate import render_observation
    from diamond_sss.evaluation.figures import save_image_grid, to_display
    from diamond_sss.evaluation.run import evaluate_run
    from diamond_sss.pipeline.run import PipelineConfig, parse_augment, run_pipeline
    from diamond_sss.training.config import short_schedule
    from diamond_sss.training.run import train_run
    from diamond_sss.training.run_folder import load_scene
    from diamond_sss.utils.io import atomic_write_text

    root = data if data is not None else embedded_dataset()
    console = Console()
    overrides = short_schedule(iterations)
    augments = parse_augment(augment)
    rows = []

    def timed(label: str, run_dir: Path, body) -> None:
        started = time.perf_counter()
        metrics = body()
        rows.append((label, run_dir, metrics, time.perf_counter() - started))

    timed("SSS-3DGS (real images only)", out / "sss3dgs", lambda: (
        train_run(root, out / "sss3dgs", regime=regime, preset="sss3dgs", overrides=overrides, resume=True,
                  show_progress=not quiet),
        evaluate_run(out / "sss3dgs", root, figures=0, show_progress=not quiet))[1])
    timed("DIAMOND-SSS (full pipeline)", out / "diamond" / "final", lambda: run_pipeline(
        root, out / "diamond", regime=regime, preset="diamond", overrides=overrides,
        config=PipelineConfig(augment=augments, prelim_run=str(out / "sss3dgs")),
        show_progress=not quiet, move_changed_run=True))
    if dense:
        timed("dense reconstruction", out / "dense", lambda: (
            train_run(root, out / "dense", regime="all", preset="diamond", overrides=overrides, resume=True,
                      show_progress=not quiet),
            evaluate_run(out / "dense", root, figures=0, show_progress=not quiet))[1])

    table = Table(title=f"{root.name}: novel views x novel lights (test split), regime {regime}")
    for column in ("method", "training images", "PSNR", "SSIM", "mask IoU", "synthetic images", "minutes"):
        table.add_column(column)
    lines = [f"# DIAMOND-SSS demo: {root.name}", "",
             (f"Sparse regime `{regime}`, {iterations} steps per reconstruction (`short_schedule`), diffusion "
             f"augmentation: {', '.join(augments) or 'none (no shipped diffusion model)'}; the DIAMOND-SSS "
             "pipeline reuses the SSS-3DGS run as its preliminary reconstruction (its minutes exclude it). "
             "Metrics on sRGB, full frame, black background, test split (novel views under novel lights)."), "",
             "| method | training images | PSNR | SSIM | mask IoU | synthetic images | minutes |",
             "|---|---|---|---|---|---|---|"]
    for label, run_dir, metrics, seconds in rows:
        synthetic = metrics.get("synthetic_images", 0)
        real = len(json.loads((run_dir / "regime.json").read_text())["observations"])
        cells = [str(real + synthetic), f"{metrics['psnr']:.2f}", f"{metrics['ssim']:.4f}",
                 f"{metrics['mask_iou']:.3f}", str(synthetic), f"{seconds / 60:.1f}"]
        table.add_row(label, *cells)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    console.print(table)

    test = OLATDataset(root, "test")
    picks = [round(i * (len(test) - 1) / 3) for i in range(4)]
    scenes = [load_scene(run_dir)[0] for _, run_dir, _, _ in rows]
    grid = [[to_display(test.load(i).rgb)] + [to_display(render_observation(s, test, i, "cpu").radiance[0])
                                             for s in scenes] for i in picks]
    figure = save_image_grid(out / "comparison.png", grid, col_labels=["ground truth", *[r[0].split(" (")[0] for r in rows]],
                             row_labels=[f"view {test.observations[i].view}, light {test.observations[i].light}"
                                         for i in picks], title=f"{root.name}, regime {regime}")
    lines += ["", f"![comparison]({figure.name})", ""]
    report = atomic_write_text(out / "report.md", "\n".join(lines) + "\n")
    console.print(f"report: {report}\nfigure: {figure}")
