"""The rounds of a finished multi-round pipeline folder as they ran: ``<out>/round<k>/final``, then ``<out>/final``."""

from __future__ import annotations

from pathlib import Path

from diamond_sss.diffusion.common.manifest import MANIFEST_NAME, read_image_manifest
from diamond_sss.pipeline.run import mask_area_ratio
from diamond_sss.utils.io import read_json


def round_metrics(run: Path) -> list[dict]:
    """Test PSNR and mask IoU of every round's final reconstruction of a pipeline folder run with ``rounds`` > 1
    (``round<k>/final``, then ``final``), as the rounds ran, with what a later round's ``pipeline.json`` recorded:
    ``mask_area`` (its repaired masks' area over the previous round's, computed from both rounds' ``repair`` folders
    for a run made before the stage recorded it) and ``kept`` (it kept the previous round's reconstruction); ``[]``
    for a single round or a training run (the rounds not evaluated yet are left out)."""
    finals = sorted((path for path in run.glob("round*/final") if path.parent.name[5:].isdigit()),
                    key=lambda path: int(path.parent.name[5:]))
    if not finals:
        return []
    numbers = [int(final.parent.name[5:]) for final in finals]
    rounds, folders = [], [final.parent for final in finals] + [run]
    for index, (number, final) in enumerate(zip([*numbers, numbers[-1] + 1], [*finals, run / "final"], strict=True)):
        metrics_file = final / "eval_test" / "metrics.json"
        if metrics_file.is_file():
            metrics = read_json(metrics_file)
            if missing := [key for key in ("psnr", "mask_iou") if key not in metrics]:
                raise ValueError(f"{metrics_file}: no {' or '.join(missing)} (an evaluation's metrics.json has both)")
            manifest = final.parent / "pipeline.json"
            stages = read_json(manifest).get("stages", {}) if manifest.is_file() else {}
            area = stages.get("repair", {}).get("mask_area_vs_previous_round")
            repaired = [folder / "repair" / MANIFEST_NAME for folder in folders[max(index - 1, 0):index + 1]]
            if area is None and index > 0 and all(path.is_file() for path in repaired):
                compared = mask_area_ratio(*(read_image_manifest(path) for path in reversed(repaired)))
                area = None if compared is None else round(compared[0], 4)
            rounds.append({"round": number, "psnr": metrics["psnr"], "mask_iou": metrics["mask_iou"],
                           "mask_area": area, "kept": "kept" in stages.get("final", {})})
    return rounds
