"""Ablation of the multi-view geometric losses (supplement Tab. 2, Fig. 16): variants x capture regimes.

Variants: the ``sss3dgs`` preset; the ``diamond`` preset without the two multi-view losses; + silhouette;
+ depth; + both; + both with targets also among the views without an image; the terms on the ``sss3dgs`` preset.
Each is trained on every regime and scored on the test split (novel views under novel lights). Runs are resumable
folders, so an interrupted ablation continues where it stopped.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.evaluation.evaluate import render_observation
from diamond_sss.evaluation.figures import save_image_grid, to_display
from diamond_sss.evaluation.run import evaluate_run
from diamond_sss.runs.folder import load_scene
from diamond_sss.training.config import DENSE_MIN_IMAGES, Losses, Schedule
from diamond_sss.training.overrides import checked_values, make_config
from diamond_sss.training.run import selected_images, train_run
from diamond_sss.utils.io import atomic_write_json, atomic_write_text

VARIANTS: dict[str, tuple[str, dict[str, float | bool | str]]] = {
    "sss3dgs": ("sss3dgs", {}),
    "diamond-no-mv": ("diamond", {"lambda_sil": 0.0, "lambda_depth": 0.0}),
    "+silhouette": ("diamond", {"lambda_depth": 0.0}),
    "+depth": ("diamond", {"lambda_sil": 0.0}),
    "+both": ("diamond", {}),
    "+both-all-targets": ("diamond", {"mv_include_unobserved_views": True}),
    "sss3dgs+silhouette": ("sss3dgs", {"lambda_sil": Losses.lambda_sil}),
    "sss3dgs+depth": ("sss3dgs", {"lambda_depth": Losses.lambda_depth}),
    "sss3dgs+both": ("sss3dgs", {"lambda_sil": Losses.lambda_sil, "lambda_depth": Losses.lambda_depth}),
    "+both-blend": ("diamond", {"mv_source_gradient": "blend"}),
    "+both-centres": ("diamond", {"mv_source_gradient": "centres"}),
    "sss3dgs+both-blend": ("sss3dgs", {"lambda_sil": Losses.lambda_sil, "lambda_depth": Losses.lambda_depth,
                                       "mv_source_gradient": "blend"}),
    "sss3dgs+both-centres": ("sss3dgs", {"lambda_sil": Losses.lambda_sil, "lambda_depth": Losses.lambda_depth,
                                         "mv_source_gradient": "centres"}),
}
"""``+both`` draws its targets among the views with an image (real or generated); ``+both-all-targets`` also among
the lattice views without one (depth term only), the default before issue 58. ``sss3dgs+...``: the terms at the
``diamond`` preset's weights on the ``sss3dgs`` preset, whose other settings score higher on sparse captures
(issue 58). Under the short-run settings (:func:`~diamond_sss.training.config.short_schedule`) a sparse regime gives
every variant those settings (``SPARSE_FROM_SSS3DGS``), so there the two families differ only in unused LPIPS weights;
pass ``--set`` or other overrides to compare the ``diamond`` preset's own. The terms move what the settings say
through the source views' depth (``multiview.source_gradient``: ``centres`` in a sparse short run,
``SPARSE_MULTIVIEW``, ``blend`` otherwise); ``...-blend`` and ``...-centres`` set it."""
DEFAULT_VARIANTS = ("sss3dgs", "diamond-no-mv", "+silhouette", "+depth", "+both", "+both-all-targets")
"""What `diamond-sss ablate` and benchmarks/ablation.py train unless told: Tab. 2's rows and the SSS-3DGS baseline."""
REGIMES = ("all", "views=5,lights=6", "views=3,lights=3")
"""Dense and the paper's two sparse regimes as counts (30 and 9 images, issue 18): the percentage forms give 2 and 1
images on the demo object's 40 x 24 lattice, too few for any method."""


@dataclass
class AblationRow:
    variant: str
    regime: str
    metrics: dict
    seconds: float


def regime_slug(regime: str) -> str:
    """A folder name for a regime spec (``views=5%,lights=5%`` -> ``views5p_lights5p``)."""
    return regime.replace("=", "").replace("%", "p").replace(",", "_")


def run_ablation(data: Path, out: Path, *, variants: Sequence[str] = tuple(VARIANTS),
                 regimes: Sequence[str] = REGIMES, iterations: int = 400, overrides: dict[str, Any] | None = None,
                 dense_overrides: dict[str, Any] | None = None, show_progress: bool = True) -> list[AblationRow]:
    """Train and evaluate every (variant, regime) with ``overrides`` (config keys, the seed among them), on a regime
    that selects a dense capture (:data:`~diamond_sss.training.config.DENSE_MIN_IMAGES` images or more) with
    ``dense_overrides`` over them (e.g. ``DENSE_SHORT_RUN``), under the variant's own; write ``ablation.json``,
    ``ablation.md`` and a figure grid."""
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ValueError(f"unknown ablation variants {unknown}; choose from {list(VARIANTS)}")
    rows = []
    seed = checked_values(overrides or {}).get("schedule.seed", Schedule.seed)
    for regime in regimes:
        dense = selected_images(data, "train", regime, seed) >= DENSE_MIN_IMAGES
        for variant in variants:
            preset, variant_overrides = VARIANTS[variant]
            run = out / regime_slug(regime) / variant
            started = time.perf_counter()
            regime_overrides = {**(overrides or {}), **((dense_overrides or {}) if dense else {})}
            config = make_config(preset, overrides={**regime_overrides, **variant_overrides, "iterations": iterations})
            train_run(data, run, config, regime=regime, resume=True, show_progress=show_progress)
            metrics = evaluate_run(run, data, split="test", figures=0, show_progress=show_progress)
            rows.append(AblationRow(variant, regime, metrics, time.perf_counter() - started))
    write_ablation_report(out, rows, data, iterations)
    save_ablation_figure(out / "ablation_grid.png", out, data, variants, regimes)
    return rows


def ablation_table(rows: Sequence[AblationRow]) -> str:
    """Markdown table of the rows (LPIPS shown as n/a when unavailable)."""
    lines = ["| regime | variant | PSNR | SSIM | LPIPS | mask IoU | minutes |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lpips = "n/a" if r.metrics.get("lpips") is None else f"{r.metrics['lpips']:.4f}"
        lines.append(f"| `{r.regime}` | {r.variant} | {r.metrics['psnr']:.2f} | {r.metrics['ssim']:.4f} | "
                     f"{lpips} | {r.metrics['mask_iou']:.3f} | {r.seconds / 60:.1f} |")
    return "\n".join(lines)


def write_ablation_report(out: Path, rows: Sequence[AblationRow], data: Path, iterations: int) -> None:
    atomic_write_json(out / "ablation.json", [{"variant": r.variant, "regime": r.regime, "seconds": r.seconds,
                                               **r.metrics} for r in rows])
    text = (f"# Multi-view loss ablation on {Path(data).name}\n\n{iterations} steps per run; test split (novel "
            f"views x novel lights).\n\n{ablation_table(rows)}\n\n![grid](ablation_grid.png)\n")
    atomic_write_text(out / "ablation.md", text)


def save_ablation_figure(path: Path, out: Path, data: Path, variants: Sequence[str], regimes: Sequence[str],
                         test_index: int = 0) -> Path:
    """Grid: one row per regime, columns ground truth then each variant, for one test image."""
    dataset = OLATDataset(data, "test")
    rows, labels = [], []
    for regime in regimes:
        row = [to_display(dataset.load(test_index).rgb)]
        for variant in variants:
            scene, _ = load_scene(out / regime_slug(regime) / variant)
            row.append(to_display(render_observation(scene, dataset, test_index, next(scene.parameters()).device)
                                  .radiance[0].cpu()))
        rows.append(row)
        labels.append(regime)
    return save_image_grid(path, rows, row_labels=labels, col_labels=["ground truth", *variants],
                           title="multi-view loss ablation (test view, test light)")
