"""Round by round, the multi-round pipeline runs already made (issue 57: when a later repair round pays).

For every pipeline folder given (a `benchmarks/regimes.py` row's folder, e.g. `<runs>/<object>/images9/repair`):
the test PSNR and mask IoU of each round's final reconstruction (`diamond_sss.pipeline.rounds.round_metrics`), the
area of the last round's repaired masks over the previous round's (`mask_area`), whether it kept the previous round's
reconstruction, and the `sss3dgs` run beside it. Rows are sorted by that mask area; the summary splits them at
`--threshold` (default: `min_round_mask_area`'s) and gives each side's mean of last round - first round. Prints the
table and writes `rounds.md` and `rounds.json` to `--out`. Nothing is trained.

    python benchmarks/rounds.py outputs/lead/runs_far/*/*/repair --out benchmarks/results/ablation/rounds
"""

from __future__ import annotations

import argparse
from pathlib import Path

from diamond_sss.pipeline.config import MIN_ROUND_MASK_AREA
from diamond_sss.pipeline.rounds import round_metrics
from diamond_sss.utils.io import atomic_write_json, atomic_write_text, read_json


def run_row(run: Path) -> dict | str:
    """One pipeline folder's rounds and its `sss3dgs` sibling's test metrics, or why it gives no row."""
    if not (run / "pipeline.json").is_file():
        return "not a pipeline folder (no pipeline.json)"
    rounds = round_metrics(run)
    if len(rounds) < 2:
        return f"{len(rounds) or 'no'} evaluated round{'s' * (len(rounds) != 1)}; two or more are compared"
    if rounds[-1]["mask_area"] is None:
        return "its last round recorded no mask area and has no repair folders to compute it from"
    baseline = run.parent / "sss3dgs" / "eval_test" / "metrics.json"
    sss = read_json(baseline) if baseline.is_file() else {}
    return {"run": str(run), "rounds": rounds, "sss3dgs": sss.get("psnr"), "sss3dgs_mask_iou": sss.get("mask_iou")}


def summary(rows: list[dict], threshold: float) -> list[dict]:
    """Below and at or above ``threshold`` (last round's mask area): runs, mask-area range, mean last - first round."""
    sides = []
    for name, side in (("below", [r for r in rows if r["rounds"][-1]["mask_area"] < threshold]),
                       ("at or above", [r for r in rows if r["rounds"][-1]["mask_area"] >= threshold])):
        if side:
            areas = [r["rounds"][-1]["mask_area"] for r in side]
            gains = [r["rounds"][-1]["psnr"] - r["rounds"][0]["psnr"] for r in side]
            ious = [r["rounds"][-1]["mask_iou"] - r["rounds"][0]["mask_iou"] for r in side]
            sides.append({"side": name, "runs": len(side), "mask_area": [min(areas), max(areas)],
                          "psnr_last_minus_first": sum(gains) / len(gains),
                          "mask_iou_last_minus_first": sum(ious) / len(ious)})
    return sides


def markdown(rows: list[dict], sides: list[dict], threshold: float, note: str) -> str:
    lines = [f"# Rounds of the pipeline runs ({note})" if note else "# Rounds of the pipeline runs", "",
             "| run | `sss3dgs` | first round | last round | masks, last / previous round | last - first |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        first, last = r["rounds"][0], r["rounds"][-1]
        sss = "-" if r["sss3dgs"] is None else f"{r['sss3dgs']:.2f} ({r['sss3dgs_mask_iou']:.3f})"
        lines.append(f"| {r['run']} | {sss} | {first['psnr']:.2f} ({first['mask_iou']:.3f}) | {last['psnr']:.2f} "
                     f"({last['mask_iou']:.3f}){' kept' if last['kept'] else ''} | {last['mask_area']:.3f} | "
                     f"{last['psnr'] - first['psnr']:+.2f} dB, IoU {last['mask_iou'] - first['mask_iou']:+.3f} |")
    lines += ["", f"Split at a mask area of {threshold}:", ""]
    lines += [f"- {s['side']}: {s['runs']} runs, masks {s['mask_area'][0]:.3f}-{s['mask_area'][1]:.3f}, last - first "
              f"round {s['psnr_last_minus_first']:+.2f} dB, mask IoU {s['mask_iou_last_minus_first']:+.3f}"
              for s in sides]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="pipeline folders (a regimes.py row's folder)")
    parser.add_argument("--out", type=Path, required=True, help="folder of rounds.md and rounds.json")
    parser.add_argument("--threshold", type=float, default=MIN_ROUND_MASK_AREA,
                        help="mask area at which the summary splits the runs")
    parser.add_argument("--note", default="", help="machine, date and settings, for the title")
    args = parser.parse_args()
    if not 0.0 <= args.threshold <= 1.0:
        parser.error(f"--threshold must be in [0, 1], got {args.threshold}")
    found = {run: run_row(run) for run in args.runs}
    for run, why in found.items():
        if isinstance(why, str):
            print(f"{run}: skipped: {why}")
    rows = sorted((row for row in found.values() if isinstance(row, dict)), key=lambda r: r["rounds"][-1]["mask_area"])
    if not rows:
        raise SystemExit("no pipeline folder given has two evaluated rounds with repaired masks to compare")
    sides = summary(rows, args.threshold)
    text = markdown(rows, sides, args.threshold, args.note)
    print(text)
    atomic_write_text(args.out / "rounds.md", text)
    atomic_write_json(args.out / "rounds.json", {"threshold": args.threshold, "summary": sides, "runs": rows})


if __name__ == "__main__":
    main()
