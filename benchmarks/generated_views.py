"""How good are a pipeline run's generated images? Each against the truth, beside the preliminary reconstruction.

For every image the ``nvs`` and ``relight`` stages (or the ``repair`` stage) of a finished
:func:`~diamond_sss.pipeline.run.run_pipeline` run generated (view ``v``, light ``l`` of the capture's lattice),
the synthetic capture's own image of ``(v, l)`` is the truth; the preliminary reconstruction (the real images only) is rendered at ``(v, l)`` beside it. PSNR, SSIM
(sRGB, full frame) and mask IoU per stage; ``wins`` is the share of images where the generated one has the higher
PSNR. A generated image adds colour the final reconstruction could not get from the preliminary one only where it
beats that render; where it does not, it can still add its silhouette (the visual hull, the mask loss).

    python benchmarks/generated_views.py --runs outputs/benchmarks/regimes_counts/demo/views5_lights6/full \
        outputs/benchmarks/regimes_counts/torus_soap_64px_64spp/views5_lights6/full --tag thirty

Writes ``<tag>.{md,json}`` and ``<tag>_grid.png`` (per run: truth | generated | preliminary render of its first
generated images) to --results.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from diamond_sss.data import OLATDataset
from diamond_sss.diffusion.common.manifest import MANIFEST_NAME, GeneratedImage, read_image_manifest
from diamond_sss.evaluation.figures import save_image_grid, to_display
from diamond_sss.evaluation.metrics import image_metrics
from diamond_sss.pipeline.agreement import load_generated
from diamond_sss.pipeline.capture import check_on_lattice
from diamond_sss.runs.folder import load_scene, render_lattice_image

RESULTS = Path(__file__).resolve().parent / "results" / "generated_views"
METRICS = ("psnr", "ssim", "mask_iou")
GRID_IMAGES = 4


def run_inputs(run: Path) -> tuple[Path, Path]:
    """The capture folder and the preliminary reconstruction of pipeline run ``run``, from its ``pipeline.json``."""
    manifest = run / "pipeline.json"
    if not manifest.is_file():
        raise SystemExit(f"--runs: {run} holds no pipeline.json (not a pipeline run folder)")
    try:
        record = json.loads(manifest.read_text())
        data = Path(record["inputs"]["data"])
        prelim = record.get("stages", {}).get("prelim", {}).get("reused") or run / "prelim"
    except json.JSONDecodeError as exc:
        raise SystemExit(f"{manifest}: not valid JSON ({exc})") from exc
    except (KeyError, TypeError, AttributeError) as exc:
        raise SystemExit(f"{manifest}: no inputs.data (the capture folder) in it") from exc
    for what, path in (("capture", data), ("preliminary reconstruction", Path(prelim))):
        if not path.exists():
            raise SystemExit(f"{manifest}: its {what} {path} is gone")
    return data, Path(prelim)


def stage_images(run: Path) -> dict[str, list[GeneratedImage]]:
    """The images each diffusion stage of ``run`` generated (stages that did not run are left out)."""
    stages = {"nvs": [item for path in sorted((run / "nvs").glob(f"*/{MANIFEST_NAME}"))
                      for item in read_image_manifest(path)]}
    relit = run / "relight" / "out" / MANIFEST_NAME
    stages["relight"] = read_image_manifest(relit) if relit.is_file() else []
    repaired = run / "repair" / MANIFEST_NAME
    stages["repair"] = read_image_manifest(repaired) if repaired.is_file() else []
    return {stage: items for stage, items in stages.items() if items}


def score_run(run: Path) -> tuple[list[dict], list[list]]:
    """Per generated image: its metrics and the preliminary render's against the truth; and the grid's images."""
    data, prelim = run_inputs(run)
    lattice = OLATDataset(data, "train")
    scene, _ = load_scene(prelim)
    rows, grid = [], []
    for stage, items in stage_images(run).items():
        for item in check_on_lattice(items, lattice):
            if not bool(lattice.presence[item.view, item.light]):
                continue
            truth = lattice.load(lattice.observation_index(item.view, item.light))
            rgb, mask = load_generated(item, lattice)
            render = render_lattice_image(scene, lattice, item.view, item.light)
            prelim_rgb, prelim_alpha = render.radiance[0].clamp(0.0, 1.0), render.gbuffer.alpha[0]
            generated = image_metrics(rgb, truth.rgb, mask, truth.mask)
            rendered = image_metrics(prelim_rgb, truth.rgb, prelim_alpha, truth.mask)
            rows.append({"run": str(run), "stage": stage, "view": item.view, "light": item.light,
                         **{f"generated_{k}": getattr(generated, k) for k in METRICS},
                         **{f"prelim_{k}": getattr(rendered, k) for k in METRICS}})
            if stage in ("nvs", "repair") and len(grid) < GRID_IMAGES:
                grid.append([to_display(truth.rgb), to_display(rgb), to_display(prelim_rgb)])
    return rows, grid


def summarise(rows: list[dict]) -> list[dict]:
    """Mean metrics per run and stage, and the share of images where the generated one has the higher PSNR."""
    table = []
    for key in dict.fromkeys((r["run"], r["stage"]) for r in rows):
        sel = [r for r in rows if (r["run"], r["stage"]) == key]
        mean = {k: sum(r[k] for r in sel) / len(sel) for k in sel[0] if k.startswith(("generated_", "prelim_"))}
        wins = sum(r["generated_psnr"] > r["prelim_psnr"] for r in sel) / len(sel)
        table.append({"run": key[0], "stage": key[1], "images": len(sel), **mean, "wins": wins})
    return table


def markdown(table: list[dict]) -> str:
    """The summary as a Markdown table."""
    lines = [("| run | stage | images | generated: PSNR / SSIM / mask IoU | preliminary render: PSNR / SSIM / mask IoU "
              "| generated - preliminary, PSNR | generated better |"),
             "|---|---|---|---|---|---|---|"]
    for r in table:
        cells = [" / ".join(f"{r[f'{who}_{k}']:.{2 if k == 'psnr' else 3}f}" for k in METRICS)
                 for who in ("generated", "prelim")]
        lines.append(f"| {r['run']} | {r['stage']} | {r['images']} | {cells[0]} | {cells[1]} | "
                     f"{r['generated_psnr'] - r['prelim_psnr']:+.2f} | {100 * r['wins']:.0f}% |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=Path, nargs="+", required=True, help="finished pipeline run folders")
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--tag", default="generated_views", help="file name of the table (<tag>.md / <tag>.json)")
    args = parser.parse_args()
    rows, grid, labels = [], [], []
    for run in args.runs:
        run_rows, run_grid = score_run(run)
        rows += run_rows
        grid += run_grid
        labels += [run.parent.parent.name] * len(run_grid)
    if not rows:
        raise SystemExit("--runs: no generated image with a true image in its capture")
    table = summarise(rows)
    text = markdown(table)
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / f"{args.tag}.json").write_text(json.dumps({"summary": table, "images": rows}, indent=2) + "\n")
    (args.results / f"{args.tag}.md").write_text(text + "\n")
    save_image_grid(args.results / f"{args.tag}_grid.png", grid, row_labels=labels,
                    col_labels=["truth", "generated", "preliminary render"],
                    title="novel views (nvs or repair): generated vs prelim")
    print(text)


if __name__ == "__main__":
    main()
