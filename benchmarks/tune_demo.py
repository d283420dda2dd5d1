"""A small hyperparameter study on the embedded demo capture: wall time per trial and the Tab. 4 analog.

Runs ``diamond-sss tune`` (one worker, SQLite) with short trials and writes the study's outputs to
``--out`` and a summary to ``--results`` (default ``benchmarks/results/tune_demo.json``). A study already in
``--out`` is resumed: ``--trials`` counts its earlier trials too.

    python benchmarks/tune_demo.py                                  # ~10 min on a loaded 2-core CPU
    python benchmarks/tune_demo.py --trials 30 --iterations 2000 --report-every 250 --device cuda
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import optuna
import torch

from diamond_sss.cli.tune_commands import tune
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.tuning.study import default_storage

RESULTS = Path(__file__).resolve().parent / "results" / "tune_demo.json"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line ``argv`` (default: the process's)."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=None, help="capture (default: the embedded demo)")
    parser.add_argument("--out", type=Path, default=Path("tune_demo"), help="the study's folder (resumed if present)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the summary JSON")
    parser.add_argument("--regime", default="views=12,lights=6")
    parser.add_argument("--trials", type=int, default=6)
    parser.add_argument("--iterations", type=int, default=60)
    parser.add_argument("--report-every", type=int, default=20)
    parser.add_argument("--downscale", type=float, default=2.0)
    parser.add_argument("--gaussians", type=int, default=2000)
    parser.add_argument("--device", default="auto")
    return parser.parse_args(argv)


def trial_sets(downscale: float, gaussians: int) -> list[str]:
    """The ``--set`` values every trial trains with: the image downscale and the number of Gaussians."""
    return [f"downscale={downscale}", f"num_gaussians={gaussians}"]


def trial_records(study: optuna.Study) -> list[dict]:
    """One record per trial: number, state, value (validation PSNR), enqueued preset, seconds, pruner reports."""
    return [{"number": t.number, "state": t.state.name, "value": t.value,
             "preset": t.user_attrs.get("preset"), "seconds": t.user_attrs.get("seconds"),
             "reports": len(t.intermediate_values)} for t in study.trials]


def demo_summary(args: argparse.Namespace, data: Path, seconds: float, study: optuna.Study, table: str) -> dict:
    """The JSON summary: settings, machine, total wall time, every trial, the best trial and the Tab. 4 text."""
    return {
        "data": str(data), "regime": args.regime, "iterations": args.iterations, "downscale": args.downscale,
        "num_gaussians": args.gaussians, "device": args.device, "cuda": torch.cuda.is_available(),
        "threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
        "seconds_total": round(seconds, 1), "trials": trial_records(study), "best": study.best_trial.number,
        "table": table,
    }


def main() -> None:
    args = parse_args()
    data = args.data or embedded_dataset("demo")
    started = time.perf_counter()
    tune(data, args.out, regime=args.regime, trials=args.trials, iterations=args.iterations,
         report_every=args.report_every, set_=trial_sets(args.downscale, args.gaussians), device=args.device)
    seconds = time.perf_counter() - started
    study = optuna.load_study(study_name="diamond-sss", storage=default_storage(args.out))
    summary = demo_summary(args, data, seconds, study, (args.out / "tab4.md").read_text())
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(summary, indent=2) + "\n")
    print(summary["table"])
    print(f"{len(summary['trials'])} trials in {seconds:.0f} s -> {args.results}")


if __name__ == "__main__":
    main()
