"""Are repaired renders better than the renders they start from? Per held-out reconstruction (issue 59).

For each finished sparse reconstruction given (a `diamond-sss train` run on a capture with the rest of its lattice,
e.g. `benchmarks/regimes.py`'s `sss3dgs` row in the lattice form), up to --most of the lattice images it did not see
are made into repair pairs (`diamond-sss repair-data`, cached in --pairs-dir) and scored against the truth: the
render's PSNR (premultiplied sRGB, full frame) beside the repaired image's, and the share of images the repair
improves.

    python benchmarks/repair_quality.py --model outputs/repair/train/model \\
        --runs outputs/lead/runs/knot_jade/images9/sss3dgs outputs/lead/runs/blob_wax/images9/sss3dgs --tag heldout

Writes ``<tag>.{md,json}`` to --results.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from diamond_sss.diffusion.repair.data import RepairPairs, read_pair_metadata, write_pairs
from diamond_sss.diffusion.repair.model import RepairModel
from diamond_sss.diffusion.repair.train import validation

RESULTS = Path(__file__).resolve().parent / "results" / "repair_quality"


def markdown(rows: list[dict], model: Path) -> str:
    lines = [f"Repair model `{model}`; PSNR dB per image, averaged (premultiplied sRGB, full frame).", "",
             "| reconstruction | capture | pairs | render | repaired | gain | repair better |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['run']} | {r['data']} | {r['pairs']} | {r['render_psnr']:.2f} | {r['repaired_psnr']:.2f} | "
                     f"{r['repaired_psnr'] - r['render_psnr']:+.2f} | {100 * r['better']:.0f}% |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, required=True, help="repair model folder")
    parser.add_argument("--runs", type=Path, nargs="+", required=True, help="finished sparse `train` run folders")
    parser.add_argument("--most", type=int, default=200, help="unseen images scored per run (0: all)")
    parser.add_argument("--pairs-dir", type=Path, default=Path("outputs/benchmarks/repair_pairs"))
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--tag", default="repair_quality")
    args = parser.parse_args()
    model = RepairModel.load(args.model)
    rows = []
    for run in args.runs:
        if not (run / "model.safetensors").is_file():
            raise SystemExit(f"--runs: {run} is not a finished reconstruction (no model.safetensors)")
        name = "_".join(run.resolve().parts[-3:])
        path = args.pairs_dir / f"{name}_most{args.most}.safetensors"
        if not path.is_file():
            write_pairs(run, path, most=args.most, show_progress=False)
        metadata = read_pair_metadata(path)
        rows.append({"run": str(run), "data": Path(metadata["data"]).name, **validation(model, RepairPairs.read([path]))})
        print(json.dumps(rows[-1]), flush=True)
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / f"{args.tag}.json").write_text(json.dumps({"model": str(args.model), "rows": rows}, indent=2) + "\n")
    text = markdown(rows, args.model)
    (args.results / f"{args.tag}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
