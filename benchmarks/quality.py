"""Reconstruction quality on the embedded demo object per capture regime and preset (issue 3).

Trains with the short CPU schedule and reports PSNR / SSIM / mask IoU on the test split (novel views under
novel lights). Runs go to outputs/benchmarks/quality (resumable); tables to benchmarks/results/quality.

    python benchmarks/quality.py --iterations 400 --presets diamond sss3dgs --regimes all "views=5%,lights=5%"
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.evaluation.ablation import regime_slug
from diamond_sss.training.config import short_schedule
from diamond_sss.training.run import evaluate_run, train_run

RESULTS = Path(__file__).resolve().parent / "results" / "quality"
RUNS = Path("outputs") / "benchmarks" / "quality"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=None, help="data folder (default: the embedded demo)")
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--presets", nargs="+", default=["diamond", "sss3dgs"])
    parser.add_argument("--regimes", nargs="+", default=["all", "views=5%,lights=5%"])
    parser.add_argument("--out", type=Path, default=RUNS, help="run folders (resumable)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="where the tables and figures are copied")
    args = parser.parse_args()
    data = args.data or embedded_dataset()
    rows = []
    for regime in args.regimes:
        for preset in args.presets:
            run = args.out / regime_slug(regime) / preset
            started = time.perf_counter()
            train_run(data, run, regime=regime, preset=preset, overrides=short_schedule(args.iterations),
                      resume=True)
            metrics = evaluate_run(run, data, split="test", figures=4)
            rows.append({"regime": regime, "preset": preset, "iterations": args.iterations,
                         "minutes": (time.perf_counter() - started) / 60, **metrics})
    lines = ["| regime | preset | steps | PSNR | SSIM | mask IoU | minutes |", "|---|---|---|---|---|---|---|"]
    lines += [f"| `{r['regime']}` | {r['preset']} | {r['iterations']} | {r['psnr']:.2f} | {r['ssim']:.4f} | "
              f"{r['mask_iou']:.3f} | {r['minutes']:.1f} |" for r in rows]
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "quality.json").write_text(json.dumps(rows, indent=2) + "\n")
    (args.results / "quality.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
