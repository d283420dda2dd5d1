"""The demo job: SSS-3DGS vs DIAMOND-SSS on a 9-image capture, with the dense reconstruction as reference.

Each reconstruction is resumable under ``out``; a run folder made with other settings (a new version's defaults,
other models) is moved aside to ``<name>.<hash>`` and made again, so nothing is lost and nothing mixed. The dense
reconstruction does not depend on the other two, so on a machine with two or more cores it trains in a second process
beside them (every run trains on one thread, ``runtime.cpu_threads``, so the numbers do not depend on this).
"""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.evaluation.evaluate import render_observation
from diamond_sss.evaluation.figures import save_image_grid, to_display
from diamond_sss.evaluation.run import evaluate_run
from diamond_sss.pipeline.config import PipelineConfig
from diamond_sss.pipeline.run import parse_augment, run_pipeline
from diamond_sss.runs.folder import load_scene
from diamond_sss.training.config import short_schedule
from diamond_sss.training.overrides import make_config
from diamond_sss.training.run import train_run
from diamond_sss.training.run_folder import move_aside_if_trained_otherwise
from diamond_sss.utils.io import atomic_write_text
from diamond_sss.utils.processes import BackgroundCall, ChildProgress, StepReporter, usable_cores

DEMO_REGIME = "views=3,lights=3"
COLUMNS = ("method", "training images", "PSNR", "SSIM", "mask IoU", "synthetic images", "minutes")


@dataclass
class DemoRow:
    """One reconstruction of the demo: its label, run folder, test metrics and wall time (seconds)."""

    label: str
    run_dir: Path
    metrics: dict
    seconds: float

    def cells(self) -> list[str]:
        """The table cells after the label (see :data:`COLUMNS`)."""
        synthetic = self.metrics.get("synthetic_images", 0)
        real = len(json.loads((self.run_dir / "regime.json").read_text())["observations"])
        return [str(real + synthetic), f"{self.metrics['psnr']:.2f}", f"{self.metrics['ssim']:.4f}",
                f"{self.metrics['mask_iou']:.3f}", str(synthetic), f"{self.seconds / 60:.1f}"]


@dataclass
class DemoResult:
    """The rows, the report and the figure of a demo run; ``moved``: run folders moved aside."""

    title: str
    rows: list[DemoRow]
    report: Path
    figure: Path
    moved: list[Path] = field(default_factory=list)


def _reconstruction(root: Path, run: Path, regime: str, preset: str, overrides: dict, show_progress: bool,
                    moved: list[Path], on_step: StepReporter | None = None) -> dict:
    """Train (or resume, or reuse when finished) one run folder and score it on the test split; ``on_step`` is
    told every step, and the run's length once it is trained."""
    config = make_config(preset, overrides=overrides)
    if (moved_run := move_aside_if_trained_otherwise(run, config)) is not None:
        moved.append(moved_run)
    result = train_run(root, run, config, regime=regime, resume=True, show_progress=show_progress, on_step=on_step)
    if on_step is not None:
        on_step(result.steps)
    return evaluate_run(run, root, figures=0, show_progress=show_progress)


def _timed_dense(root: Path, run: Path, iterations: int, show_progress: bool,
                 on_step: StepReporter | None = None) -> tuple[dict, float, list[Path]]:
    """The dense reconstruction (every image, ``diamond`` preset, dense budget): metrics, seconds, moved folders."""
    started = time.perf_counter()
    moved: list[Path] = []
    metrics = _reconstruction(root, run, "all", "diamond", short_schedule(iterations, dense=True), show_progress,
                              moved, on_step)
    return metrics, time.perf_counter() - started, moved


def run_demo(out: Path = Path("outputs/demo"), data: Path | None = None, regime: str = DEMO_REGIME,
             iterations: int = 1000, augment: str = "auto", dense: bool = True, parallel: bool = True,
             show_progress: bool = True) -> DemoResult:
    """SSS-3DGS (``sss3dgs`` preset, real images only), the DIAMOND-SSS pipeline (the SSS-3DGS run reused as its
    preliminary reconstruction, the shipped models of ``augment``, the final reconstruction)
    and, with ``dense``, DIAMOND-SSS on every image; all with ``short_schedule(iterations)`` (the pipeline's final
    reconstruction with its own settings, the dense one with its dense budget). With ``parallel`` and two or more
    cores, the dense one trains in a second process while the other two train here (its progress bar here follows
    the steps it reports). Writes ``report.md`` and ``comparison.png`` into ``out``."""
    root = Path(data) if data is not None else embedded_dataset()
    out = Path(out)
    overrides = short_schedule(iterations)
    augments = parse_augment(augment)
    rows: list[DemoRow] = []
    moved: list[Path] = []

    def timed(label: str, run_dir: Path, body) -> None:
        started = time.perf_counter()
        metrics = body()
        rows.append(DemoRow(label, run_dir, metrics, time.perf_counter() - started))

    background = dense and parallel and usable_cores() >= 2
    with contextlib.ExitStack() as stack:  # leaving it early (failed, interrupted) terminates the second process
        dense_job = None
        if background:
            progress = (stack.enter_context(ChildProgress(iterations, "dense reconstruction (second process)"))
                        if show_progress else None)
            dense_job = BackgroundCall(_timed_dense, (root, out / "dense", iterations, False,
                                                      progress.reporter if progress else None),
                                       label=f"the dense reconstruction ({out / 'dense'})")
            stack.callback(dense_job.stop)
        timed("SSS-3DGS (real images only)", out / "sss3dgs",
              lambda: _reconstruction(root, out / "sss3dgs", regime, "sss3dgs", overrides, show_progress, moved))
        timed("DIAMOND-SSS (full pipeline)", out / "diamond" / "final", lambda: run_pipeline(
            root, out / "diamond", regime=regime, preset="diamond",
            overrides=short_schedule(iterations, pipeline_final=True),
            config=PipelineConfig(augment=augments, prelim_run=str(out / "sss3dgs")),
            show_progress=show_progress, move_changed_run=True))
        if dense:
            metrics, seconds, dense_moved = (dense_job.result() if dense_job is not None
                                             else _timed_dense(root, out / "dense", iterations, show_progress))
            moved += dense_moved
            rows.append(DemoRow("dense reconstruction", out / "dense", metrics, seconds))

    title = f"{root.name}: novel views x novel lights (test split), regime {regime}"
    lines = [f"# DIAMOND-SSS demo: {root.name}", "",
             (f"Sparse regime `{regime}`, {iterations} steps per reconstruction (`short_schedule`), "
              f"augmentation: {', '.join(augments) or 'none (no shipped model)'}; the DIAMOND-SSS "
              "pipeline reuses the SSS-3DGS run as its preliminary reconstruction (its minutes exclude it). "
              "Metrics on sRGB, full frame, black background, test split (novel views under novel lights)."), "",
             "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += [f"| {row.label} | " + " | ".join(row.cells()) + " |" for row in rows]
    test = OLATDataset(root, "test")
    picks = [round(i * (len(test) - 1) / 3) for i in range(4)]
    scenes = [load_scene(row.run_dir)[0] for row in rows]
    grid = [[to_display(test.load(i).rgb)] + [to_display(render_observation(s, test, i, "cpu").radiance[0])
                                             for s in scenes] for i in picks]
    figure = save_image_grid(out / "comparison.png", grid,
                             col_labels=["ground truth", *[row.label.split(" (")[0] for row in rows]],
                             row_labels=[f"view {test.observations[i].view}, light {test.observations[i].light}"
                                         for i in picks], title=f"{root.name}, regime {regime}")
    lines += ["", f"![comparison]({figure.name})", ""]
    report = atomic_write_text(out / "report.md", "\n".join(lines) + "\n")
    return DemoResult(title=title, rows=rows, report=report, figure=figure, moved=moved)
