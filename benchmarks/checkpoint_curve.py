"""Test metrics along a run: every checkpoint's scene, and the saved model, scored on the test split.

What it answers: would stopping a run earlier (or picking its best checkpoint) have given a better model? A run
keeps its newest two checkpoints unless trained with ``--set keep_checkpoints=0`` (every one); a pipeline run's final
reconstruction is ``<pipeline>/final``. Each checkpoint's ``scene.safetensors`` is that step's model (the running
mean of ``schedule.average_last``, kept beside it, is not scored); the saved model is the row of the run's last step.

    OMP_NUM_THREADS=1 python benchmarks/regimes.py --iterations 3000 --objects torus:soap \
        --regimes "views=5,lights=6" --methods full --pipeline-set checkpoint_every=250 keep_checkpoints=0 --tag ck250all
    python benchmarks/checkpoint_curve.py \
        --runs outputs/benchmarks/regimes_counts/torus_soap_64px_64spp/views5_lights6/full_ck250all/final \
        --tag ck250_curves --note "2-core CPU, 2026-11-29"

Prints the table and writes ``<tag>.{md,json,png}`` (PSNR against the step, a line per run) to --results. The data
is each run's ``data.json`` capture unless --data names one per run.
"""

from __future__ import annotations

import argparse
import json
import textwrap
from pathlib import Path

import torch

from diamond_sss.data import DataError, OLATDataset
from diamond_sss.evaluation.evaluate import evaluate_scene
from diamond_sss.scene.io import read_scene
from diamond_sss.training.checkpoint import checkpoint_folders
from diamond_sss.training.overrides import load_run_config
from diamond_sss.utils.io import read_json

RESULTS = Path(__file__).resolve().parent / "results" / "regimes"
METRICS = ("psnr", "ssim", "mask_iou")


def scored_states(run: Path) -> list[tuple[int, Path]]:
    """``(step, scene file)`` of every checkpoint of ``run`` and of its saved model (at the run's last step), by step."""
    model = run / "model.safetensors"
    summary = run / "train_summary.json"
    if not (model.is_file() and summary.is_file()):
        raise SystemExit(f"--runs: {run} is not a finished run ({model} or {summary} is missing)")
    states = {recorded_step(folder / "state.json", "step"): folder / "scene.safetensors"
              for folder in checkpoint_folders(run)}
    states[recorded_step(summary, "steps")] = model
    return sorted(states.items())


def recorded_step(path: Path, key: str) -> int:
    """The step count that JSON file ``path`` records under ``key``."""
    value = read_json(path).get(key)
    if not isinstance(value, int):
        raise DataError(f"{path}: key '{key}': expected a step count, got {value!r}")
    return value


def recorded_data(run: Path) -> Path:
    """The capture ``run`` was trained on, as its ``data.json`` records it."""
    data = read_json(run / "data.json").get("data")
    if not isinstance(data, str):
        raise DataError(f"{run / 'data.json'}: key 'data': expected the capture's folder, got {data!r}")
    return Path(data)


def curve(run: Path, data: Path, device: torch.device) -> list[dict]:
    """The test metrics of every state of ``run`` (:func:`scored_states`) on ``data``'s test split."""
    cfg = load_run_config(run)
    dataset = OLATDataset(data, "test", downscale=cfg.runtime.downscale)
    rows = []
    for step, path in scored_states(run):
        scene = read_scene(path, cfg.shading, device)
        summary = evaluate_scene(scene, dataset, show_progress=False).summary
        rows.append({"step": step, **{key: summary[key] for key in METRICS}})
        print(f"{run}  step {step:6d}  PSNR {summary['psnr']:.2f}  mask IoU {summary['mask_iou']:.3f}", flush=True)
    return rows


def markdown(curves: dict[str, list[dict]], note: str) -> str:
    """A table of PSNR (mask IoU) per step, a column per run, and each run's best step."""
    names = list(curves)
    steps = sorted({row["step"] for rows in curves.values() for row in rows})
    by_step = {name: {row["step"]: row for row in rows} for name, rows in curves.items()}
    lines = [f"Test split (novel views under novel lights), sRGB, full frame; PSNR dB (mask IoU). {note}".strip(), "",
             "| step | " + " | ".join(f"`{name}`" for name in names) + " |", "|---" * (len(names) + 1) + "|"]
    for step in steps:
        cells = [f"{by_step[n][step]['psnr']:.2f} ({by_step[n][step]['mask_iou']:.3f})" if step in by_step[n] else "-"
                 for n in names]
        lines.append(f"| {step} | " + " | ".join(cells) + " |")
    for name, rows in curves.items():
        best, last = max(rows, key=lambda row: row["psnr"]), rows[-1]
        lines.append(f"\n`{name}`: best at step {best['step']} ({best['psnr']:.2f} dB), "
                     f"{best['psnr'] - last['psnr']:+.2f} dB over the saved model.")
    return "\n".join(lines) + "\n"


def save_figure(path: Path, curves: dict[str, list[dict]], title: str) -> None:
    """PSNR against the step, a line per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6, 3.5))
    for name, rows in curves.items():
        axis.plot([row["step"] for row in rows], [row["psnr"] for row in rows], marker="o", markersize=3, label=name)
    axis.set_xlabel("step")
    axis.set_ylabel("test PSNR (dB)")
    axis.set_title(textwrap.fill(title, 90), fontsize=8)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def run_name(run: Path) -> str:
    """A short name for ``run``: its folder and the two above it (object / regime / method for a benchmark run)."""
    return "/".join(run.resolve().parts[-4:-1] if run.name == "final" else run.resolve().parts[-3:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=Path, nargs="+", required=True, help="finished reconstruction run folders")
    parser.add_argument("--data", type=Path, nargs="*", default=[],
                        help="the capture of each run, in order (default: the one its data.json records)")
    parser.add_argument("--device", default="cpu", help="cpu | cuda")
    parser.add_argument("--tag", default="checkpoint_curve")
    parser.add_argument("--note", default="", help="a line for the Markdown (machine, date)")
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.data and len(args.data) != len(args.runs):
        raise SystemExit(f"--data: {len(args.data)} captures for {len(args.runs)} runs (give one per run, or none)")
    try:
        datas = args.data or [recorded_data(run) for run in args.runs]
        curves = {run_name(run): curve(run, data, torch.device(args.device)) for run, data in zip(args.runs, datas)}
    except ValueError as exc:  # bad input (DataError among them): the message names the file
        raise SystemExit(f"checkpoint_curve: {exc}") from exc
    table = markdown(curves, args.note)
    print(table)
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / f"{args.tag}.md").write_text(table)
    (args.results / f"{args.tag}.json").write_text(json.dumps({"note": args.note, "curves": curves}, indent=1))
    save_figure(args.results / f"{args.tag}.png", curves, args.note or args.tag)


if __name__ == "__main__":
    main()
