"""Multi-view loss ablation (issue 4; supplement Tab. 2, Fig. 16) on the embedded demo object.

{sss3dgs, diamond without multi-view losses, + silhouette, + depth, + both, + both with targets also among the
views without an image} x {all, views=5,lights=6 (30 images),
views=3,lights=3 (9 images)}, each trained with the short CPU schedule and scored on novel views under novel lights.
Runs go to outputs/benchmarks/ablation (resumable); ablation.json, ablation.md and ablation_grid.png are
copied to benchmarks/results/ablation.

    python benchmarks/ablation.py --iterations 400
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.experiments.ablation import DEFAULT_VARIANTS, REGIMES, VARIANTS, ablation_table, run_ablation
from diamond_sss.training.config import DENSE_SHORT_RUN, short_schedule

RESULTS = Path(__file__).resolve().parent / "results" / "ablation"
RUNS = Path("outputs") / "benchmarks" / "ablation"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=None, help="data folder (default: the embedded demo)")
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--regimes", nargs="+", default=list(REGIMES))
    parser.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--out", type=Path, default=RUNS, help="run folders (resumable)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="where the tables and figures are copied")
    args = parser.parse_args()
    data = args.data or embedded_dataset()
    rows = run_ablation(data, args.out, variants=args.variants, regimes=args.regimes, iterations=args.iterations,
                        overrides=short_schedule(args.iterations), dense_overrides=DENSE_SHORT_RUN)
    print(ablation_table(rows))
    args.results.mkdir(parents=True, exist_ok=True)
    for name in ("ablation.json", "ablation.md", "ablation_grid.png"):
        shutil.copyfile(args.out / name, args.results / name)


if __name__ == "__main__":
    main()
