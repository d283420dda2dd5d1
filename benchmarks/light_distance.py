"""Novel-light quality against the light's distance from the training lights (issue 17).

A run trained on some of a capture's lights (``quality.py --regime "views=all,lights=24"`` on a capture rendered
with more lights) is scored on some of its training views under every light of the capture; each light is placed
by its angle, seen from the scene centre, to the nearest light the run was trained on (0 deg: the run's own
training images). Prints a table of PSNR per angle bin and writes it as Markdown and JSON with a figure (PSNR of
each light against its angle).

    python benchmarks/light_distance.py --data outputs/lights/bunny_wax_96 \
        --run outputs/benchmarks/quality/bunny_wax_96/viewsall_lights24/l24-70a282a2 --views 8
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from diamond_sss.data.dataset import OLATDataset, directions_from
from diamond_sss.data.errors import DataError
from diamond_sss.data.regimes import nearest_angle_deg
from diamond_sss.evaluation.evaluate import evaluate_scene
from diamond_sss.runs.folder import load_scene
from diamond_sss.utils.io import atomic_write_json, atomic_write_text

RESULTS = Path(__file__).resolve().parent / "results" / "quality" / "light_distance"
BIN_EDGES = (0.0, 1.0, 8.0, 12.0, 16.0, 20.0, 25.0, 35.0)


def check_regime(regime: dict, path: Path, num_lights: int, data: Path) -> None:
    """Stop, naming the file and key, unless ``regime`` (a run's ``regime.json``) lists views and lights that
    ``data``'s lattice of ``num_lights`` lights holds."""
    for key in ("views", "lights"):
        if not isinstance(regime.get(key), list) or not regime[key]:
            raise SystemExit(f"--run: {path}: key '{key}': expected a non-empty list of indices")
    if max(regime["lights"]) >= num_lights:
        raise SystemExit(f"--run: {path}: light {max(regime['lights'])} is not in --data {data} (lights "
                         f"0..{num_lights - 1}): was the run trained on another capture?")


def spread_views(views: list[int], count: int) -> list[int]:
    """``count`` of ``views`` evenly spread through the list (all of them when ``count`` is 0 or larger)."""
    if count <= 0 or count >= len(views):
        return list(views)
    return [views[math.floor((i + 0.5) * len(views) / count)] for i in range(count)]


def bin_rows(angles: list[float], psnrs: list[float], edges: tuple[float, ...] = BIN_EDGES) -> list[dict]:
    """Lights grouped by angle into ``[edges[i], edges[i+1])`` (the last bin open above): per bin the lights, their
    mean angle and the mean of their PSNRs. Empty bins are left out."""
    rows = []
    for i, low in enumerate(edges):
        high = edges[i + 1] if i + 1 < len(edges) else math.inf
        members = [(a, p) for a, p in zip(angles, psnrs, strict=True) if low <= a < high]
        if members:
            rows.append({"from_deg": low, "to_deg": high, "lights": len(members),
                         "mean_angle_deg": sum(a for a, _ in members) / len(members),
                         "psnr": sum(p for _, p in members) / len(members)})
    return rows


def markdown(rows: list[dict], title: str) -> str:
    lines = [title, "", "| angle to the nearest training light (deg) | lights | mean angle | PSNR |", "|---|---|---|---|"]
    for r in rows:
        upper = "" if math.isinf(r["to_deg"]) else f"{r['to_deg']:.0f}"
        lines.append(f"| {r['from_deg']:.0f}-{upper} | {r['lights']} | {r['mean_angle_deg']:.1f} | {r['psnr']:.2f} |")
    return "\n".join(lines)


def save_figure(path: Path, angles: list[float], psnrs: list[float], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(5, 3.5))
    axis.scatter(angles, psnrs, s=12)
    axis.set_xlabel("angle to the nearest training light (deg)")
    axis.set_ylabel("PSNR (dB), mean over the views")
    axis.set_title(title, fontsize=9)
    axis.grid(alpha=0.3)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="the capture the run was trained on")
    parser.add_argument("--run", type=Path, required=True, help="run folder (regime.json, model.safetensors)")
    parser.add_argument("--views", type=int, default=8, help="training views scored, evenly spread (0: all)")
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--tag", default=None, help="file name of the table (default: the run folder's name)")
    args = parser.parse_args()
    regime_path = args.run / "regime.json"
    if not regime_path.is_file():
        raise SystemExit(f"--run: {regime_path} not found (a run folder of `diamond-sss train` or quality.py)")
    regime = json.loads(regime_path.read_text())
    try:
        train = OLATDataset(args.data, "train")
    except DataError as exc:
        raise SystemExit(f"--data: {exc}") from exc
    check_regime(regime, regime_path, train.num_lights, args.data)
    center = train.bounds.center
    directions = directions_from(train.light_positions, center)
    angles = nearest_angle_deg(directions, directions[regime["lights"]]).tolist()
    views = spread_views(regime["views"], args.views)
    indices = [i for i, obs in enumerate(train.observations) if obs.view in set(views)]
    scene, _ = load_scene(args.run, torch.device("cpu"))
    evaluation = evaluate_scene(scene, train.subset(indices))
    per_light: dict[int, list[float]] = {}
    for _, light, metrics in evaluation.rows:
        per_light.setdefault(light, []).append(metrics.psnr)
    lights = sorted(per_light)
    light_angles = [angles[light] for light in lights]
    light_psnrs = [sum(per_light[light]) / len(per_light[light]) for light in lights]
    rows = bin_rows(light_angles, light_psnrs)
    tag = args.tag or args.run.name
    title = (f"{args.run} on {args.data.name}: {len(views)} training views under all {len(angles)} lights "
             f"({len(regime['lights'])} trained on)")
    text = markdown(rows, title)
    atomic_write_text(args.results / f"{tag}.md", text + f"\n\n![PSNR per light]({tag}.png)\n")
    atomic_write_json(args.results / f"{tag}.json", {
        "run": str(args.run), "data": str(args.data), "views": views, "bins": rows,
        "lights": [{"light": light, "angle_deg": a, "psnr": p} for light, a, p in zip(lights, light_angles, light_psnrs,
                                                                                       strict=True)]})
    save_figure(args.results / f"{tag}.png", light_angles, light_psnrs,
                f"{args.run.name} on {args.data.name}\n{len(views)} training views x {len(angles)} lights "
                f"({len(regime['lights'])} trained on)")
    print(text)


if __name__ == "__main__":
    main()
