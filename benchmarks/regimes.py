"""What each stage of DIAMOND-SSS adds in the paper's sparse regimes, given as counts (issue 18).

Regimes: `views=3,lights=3` (9 images, the paper's 3% x 3%) and `views=5,lights=6` (30 images, 5% x 5%), and
the dense reference (`dense`: the `diamond` preset on every image). Rows per object, regime and stage:
`sss3dgs` (real images only); `+mv` (the `diamond` preset: + multi-view losses); `+relight` (+ relighting
diffusion); `full` (+ novel-view diffusion: the full pipeline); `repair` (the pipeline with `--augment repair`, issue
59: the preliminary reconstruction's renders at the same targets, repaired), plus the mean over objects. The pipeline rows
reuse the `sss3dgs` run as their preliminary reconstruction and run once per --real-shares value (the pipeline's
`min_real_share`; rows and folders of a value other than the default `auto`, n / (n + 9) for n real images, are
named e.g. `full_share0`) and per
--agreement-powers value (the pipeline's `agreement_power`; other than the default 0: e.g. `full_agree1`). Every
method trains for the same steps.
Objects: data folders or `shape:material` pairs never used for fine-tuning the diffusion models (those are
torus/jade, bust/marble, blob/soap, sphere/skin), rendered once with `diamond-sss synth` into
outputs/benchmarks/objects. Metrics on the test split (novel views under novel lights).

    python benchmarks/regimes.py --iterations 1000 --objects src/diamond_sss/assets/data/demo torus:soap blob:marble \
        --real-shares 0.5 0

Capture forms (--forms): `lattice` draws each regime from the whole capture (the lattice-aware pipeline finds the
cameras and lights the regime left out); `sparse` first writes the regime's images as a capture of their own
(`diamond-sss subset`, into <out>/captures) and runs every method on it with regime `all`: a user's own sparse
capture, on which the pipeline places the cameras and lights it generates (`pipeline/rig.py`). Held-out objects of
another rig: `scripts/make_heldout_data.sh`.

Runs go to --out (resumable: a second call with the same arguments only collects); regimes.json, regimes.md and
regimes_grid.png go to --results; a pipeline row of several rounds also gives each round's test PSNR and mask IoU
(`rounds`, the last section of regimes.md). --noise-ceilings adds each rendered capture's noise ceiling (its test split
rendered again with independent noise, once, into <out>/noise_reference; as `quality.py` does for the demo). The
targets: at 9 images `full` beats `sss3dgs` by >= 2 dB PSNR and in mask IoU; at 30 images `full` is within 2 dB of
`dense` (checked for every `full` variant); issue 57's, in both forms: `full` - `sss3dgs` >= +2 dB at 9 images
and >= +1 dB at 30.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import fields
from pathlib import Path
from typing import Any

from diamond_sss.cli.synth_commands import synth
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.errors import DataError
from diamond_sss.data.export import export_regime
from diamond_sss.evaluation.evaluate import render_observation
from diamond_sss.evaluation.figures import save_image_grid, to_display
from diamond_sss.evaluation.noise import noise_ceiling
from diamond_sss.evaluation.run import evaluate_run
from diamond_sss.experiments.ablation import regime_slug
from diamond_sss.pipeline.rounds import round_metrics
from diamond_sss.pipeline.run import PipelineConfig, checked_config, run_pipeline
from diamond_sss.runs.folder import load_scene
from diamond_sss.synth.render import noise_reference_config, synthesize
from diamond_sss.training.config import short_schedule
from diamond_sss.training.overrides import make_config
from diamond_sss.training.run import train_run
from diamond_sss.training.run_folder import move_aside_if_trained_otherwise
from diamond_sss.utils.io import read_json

RESULTS = Path(__file__).resolve().parent / "results" / "regimes"
RUNS = Path("outputs") / "benchmarks" / "regimes_counts"
OBJECTS = Path("outputs") / "benchmarks" / "objects"
NINE, THIRTY = "views=3,lights=3", "views=5,lights=6"
REGIMES = (NINE, THIRTY)
NINE_IMAGES, THIRTY_IMAGES = (NINE, "images=9"), (THIRTY, "images=30")
"""The regimes each target applies to (counts of views x lights, or of images on an incomplete lattice)."""
FORMS = ("lattice", "sparse")
METHODS = ("sss3dgs", "+mv", "+relight", "full", "repair")
LABELS = {"sss3dgs": "sss3dgs (real images only)", "+mv": "+ multi-view losses", "+relight": "+ relighting",
          "full": "+ novel views (full pipeline)", "repair": "render repair instead of the two diffusion stages",
          "dense": "dense reconstruction (all images)"}
PIPELINE_METHODS = ("+relight", "full", "repair")
"""The methods run by the pipeline (a preliminary reconstruction, generated images, a final one)."""
DEFAULT_OBJECTS = ("src/diamond_sss/assets/data/demo", "torus:soap", "blob:marble")
METRICS = ("psnr", "ssim", "mask_iou")
DEFAULT_SHARE = PipelineConfig().min_real_share
DEFAULT_POWER = PipelineConfig().agreement_power


def resolve_object(spec: str, size: int, spp: int) -> Path:
    """An existing data folder as it is, else ``shape:material`` rendered once (40 x 24 lattice, 8 x 6 test)."""
    path = Path(spec)
    if path.is_dir():
        return path
    if spec.count(":") != 1:
        raise SystemExit(f"--objects: {spec!r} is neither a data folder nor a shape:material pair")
    shape, material = spec.split(":")
    folder = OBJECTS / f"{shape}_{material}_{size}px_{spp}spp"
    if not (folder / "transforms_test.json").is_file():
        synth(shape=shape, material=material, out=folder, size=size, spp=spp, seed=7)
    return folder


def noise_ceiling_of(data: Path, references: Path) -> float | None:
    """The noise ceiling (dB) of ``data``'s test split when ``data`` is a `diamond-sss synth` capture (it has a
    ``meta.json``): the split rendered again with independent noise into ``references/<name>`` once (Mitsuba),
    then PSNR(first, second) + 3.01 dB (:func:`noise_ceiling`); ``None`` for any other capture."""
    if not (data / "meta.json").is_file():
        return None
    reference = references / data.name
    if not (reference / "transforms_test.json").is_file():
        try:
            synthesize(noise_reference_config(data, reference))
        except DataError as exc:
            raise SystemExit(f"--noise-ceilings: {exc}") from exc
    return noise_ceiling(OLATDataset(data, "test"), OLATDataset(reference, "test"))["ceiling_psnr"]


def share_value(text: str) -> float | None:
    """A --real-shares value: ``auto`` (the pipeline's default, ``None``) or a number."""
    return None if text == "auto" else float(text)


def pipeline_setting(key: str, annotation: str, text: str) -> Any:
    """A --pipeline-set value as the :class:`PipelineConfig` field ``key`` of type ``annotation`` (e.g.
    ``int | None``) takes it: ``None`` for an optional field, a tuple of the comma-separated items for
    ``tuple[str, ...]`` (``augment=nvs``), else the field's scalar type."""
    scalar = annotation.removesuffix(" | None")
    if text == "None" and scalar != annotation:
        return None
    if scalar == "tuple[str, ...]":
        return tuple(item for item in text.split(",") if item)
    if scalar == "bool":
        if text.lower() not in ("true", "false"):
            raise SystemExit(f"--pipeline-set {key}={text}: {key} takes true or false")
        return text.lower() == "true"
    try:
        return {"int": int, "float": float}.get(scalar, str)(text)
    except ValueError:
        raise SystemExit(f"--pipeline-set {key}={text}: {key} takes {annotation}") from None


def variant_name(method: str, real_share: float | None = DEFAULT_SHARE, agreement_power: float = DEFAULT_POWER,
                 tag: str = "") -> str:
    """``full`` at the pipeline's default real share and agreement power, ``full_share0`` at share 0,
    ``full_agree1`` at power 1, ``full_<tag>`` with --pipeline-set, and so on; other methods as they are."""
    if method in ("sss3dgs", "+mv", "dense"):
        return method
    share = "" if real_share is None else f"_share{round(100 * real_share)}"
    power = "" if agreement_power == DEFAULT_POWER else f"_agree{agreement_power:g}"
    return f"{method}{share}{power}{f'_{tag}' if tag else ''}"


def variant_label(name: str) -> str:
    """The table's label of a :func:`variant_name`, e.g. ``full_share30_agree0`` ->
    ``+ novel views (full pipeline) [min_real_share 0.3, agreement_power 0]``."""
    method, *suffixes = name.split("_")
    settings = [f"min_real_share {int(suffix[5:]) / 100:g}" if suffix.startswith("share")
                else f"agreement_power {suffix[5:]}" if suffix.startswith("agree") else suffix
                for suffix in suffixes]
    return LABELS[method] + (f" [{', '.join(settings)}]" if settings else "")


def run_method(method: str, data: Path, runs: Path, regime: str, iterations: int,
               real_share: float | None = DEFAULT_SHARE, agreement_power: float = DEFAULT_POWER,
               pipeline_set: dict[str, str] | None = None, tag: str = "", seed: int = 0) -> tuple[Path, dict]:
    """Train and evaluate one method in ``runs/<variant_name>``; returns its final run folder and test metrics
    (+ image counts). The pipeline methods reuse ``runs/sss3dgs`` as their preliminary reconstruction."""
    overrides = {**short_schedule(iterations, dense=method == "dense", pipeline_final=method in PIPELINE_METHODS),
                 "seed": seed}
    if method in ("sss3dgs", "+mv", "dense"):
        run = runs / method
        preset = "sss3dgs" if method == "sss3dgs" else "diamond"
        config = make_config(preset, overrides=overrides)
        move_aside_if_trained_otherwise(run, config)  # settings changed since: again
        if not (run / "model.safetensors").is_file():  # a finished run is not resumed (that retrains its last part)
            train_run(data, run, config, regime="all" if method == "dense" else regime, resume=True,
                      show_progress=False)
        metrics = evaluate_run(run, data, figures=0, show_progress=False)
        real = len(json.loads((run / "regime.json").read_text())["observations"])
        return run, {**metrics, "real_images": real, "synthetic_images": 0, "real_share": 1.0}
    prelim = runs / "sss3dgs"
    settings = pipeline_set or {}
    pipeline_keys = {f.name: f.type for f in fields(PipelineConfig)}
    given = {key: pipeline_setting(key, pipeline_keys[key], value) for key, value in settings.items()
             if key in pipeline_keys}
    given.setdefault("augment", {"+relight": ("relight",), "repair": ("repair",)}.get(method, ("nvs", "relight")))
    config = checked_config(PipelineConfig(prelim_run=str(prelim), min_real_share=real_share,
                                           agreement_power=agreement_power, **given))  # before any training
    if not (prelim / "model.safetensors").is_file():
        run_method("sss3dgs", data, runs, regime, iterations, seed=seed)
    folder = runs / variant_name(method, real_share, agreement_power, tag)
    training = {key: value for key, value in settings.items() if key not in pipeline_keys}
    metrics = run_pipeline(data, folder, regime=regime, preset="diamond", overrides={**overrides, **training},
                           seed=seed, config=config, show_progress=False, move_changed_run=True)
    return folder / "final", metrics


def recorded(run: Path) -> tuple[Path, dict] | None:
    """The final run folder and test metrics (+ image counts) that ``run`` (a training run or a pipeline folder)
    recorded when it was evaluated, or ``None``."""
    metrics_file = run / "eval_test" / "metrics.json"
    if metrics_file.is_file():
        real = len(json.loads((run / "regime.json").read_text())["observations"])
        return run, {**json.loads(metrics_file.read_text()), "real_images": real, "synthetic_images": 0,
                     "real_share": 1.0}
    manifest = run / "pipeline.json"
    stages = json.loads(manifest.read_text()).get("stages", {}) if manifest.is_file() else {}
    if "eval" not in stages:
        return None
    final = stages["final"]
    return run / "final", {**stages["eval"], **{key: final[key] for key in ("real_images", "synthetic_images",
                                                                          "real_share")}}


def run_minutes(run: Path) -> float | None:
    """The minutes ``run`` recorded: a training run's training (``train_summary.json``), a pipeline folder's stages
    over all its rounds (:func:`stage_seconds`; a reused preliminary reconstruction records 0 s); ``None`` when it
    recorded none."""
    summary = run / "train_summary.json"
    if summary.is_file():
        seconds = read_json(summary).get("seconds")
        return None if seconds is None else seconds / 60
    if (run / "pipeline.json").is_file():
        return sum(stage_seconds(run).values()) / 60
    return None


def stage_seconds(run: Path) -> dict[str, float]:
    """Seconds of each stage a pipeline folder recorded, summed over its rounds (``pipeline.json`` and
    ``round<k>/pipeline.json``); ``{}`` for a training run."""
    totals: dict[str, float] = {}
    for manifest in [*sorted(run.glob("round*/pipeline.json")), run / "pipeline.json"]:
        stages = read_json(manifest).get("stages", {}) if manifest.is_file() else {}
        for name, stage in stages.items():
            if "seconds" in stage:
                totals[name] = totals.get(name, 0.0) + stage["seconds"]
    return totals


def rounds_lines(rows: list[dict]) -> list[str]:
    """Each pipeline row's test PSNR (mask IoU) round by round, as Markdown bullets, a later round's mask area against
    the round before in brackets and ``kept`` where it kept that round's reconstruction; none when no row has
    rounds."""

    def step(item: dict) -> str:
        area = "" if item.get("mask_area") is None else f"[masks {100 * item['mask_area']:.1f}%] "
        return f"{area}{item['psnr']:.2f} ({item['mask_iou']:.3f}){' kept' if item.get('kept') else ''}"

    return [f"- {r['object']}, {r.get('form', 'lattice')} `{r['regime']}`, {r['method']}: "
            + " -> ".join(step(item) for item in r["rounds"]) for r in rows if len(r.get("rounds", [])) > 1]


def sparse_capture(data: Path, out: Path, regime: str, seed: int) -> Path:
    """The ``sparse`` form of ``data`` under ``regime``: its images written as a capture of their own into
    ``out/captures/<name>_<regime>[_seed<N>]`` once (``diamond-sss subset``)."""
    folder = out / "captures" / f"{data.name}_{regime_slug(regime)}{f'_seed{seed}' if seed else ''}"
    if not (folder / "subset.json").is_file():
        export_regime(data, folder, regime, seed=seed)
    return folder


def mean_rows(rows: list[dict]) -> list[dict]:
    """One row per (form, regime, method): the mean of each metric over the objects."""
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row.get("form", "lattice"), row["regime"], row["method"]), []).append(row)
    return [{"object": f"mean ({len(group)})", "form": form, "regime": regime, "method": method,
             **{key: sum(r[key] for r in group) / len(group) for key in (*METRICS, "synthetic_images")}}
            for (form, regime, method), group in groups.items()]


def target_lines(rows: list[dict]) -> list[str]:
    """The targets per object, form and for the mean, for every ``full`` variant, as Markdown bullets: at 9 images
    ``full`` - ``sss3dgs`` >= +2 dB with a higher mask IoU; at 30 images ``full`` - ``sss3dgs`` >= +1 dB and (the
    lattice form, issue 18's) ``full`` within 2 dB of ``dense``."""
    score = {(r["object"], r.get("form", "lattice"), r["regime"], r["method"]): r for r in rows}
    lines = []
    for full_name in dict.fromkeys(r["method"] for r in rows if r["method"].startswith(("full", "repair"))):
        for name, form, regime in dict.fromkeys((r["object"], r.get("form", "lattice"), r["regime"]) for r in rows):
            full, base = score.get((name, form, regime, full_name)), score.get((name, form, regime, "sss3dgs"))
            where = f"{name}, {form} `{regime}`"
            if full and base and regime in NINE_IMAGES:
                gain, iou = full["psnr"] - base["psnr"], full["mask_iou"] - base["mask_iou"]
                met = gain >= 2.0 and iou > 0
                lines.append(f"- {where}: {full_name} - sss3dgs = {gain:+.2f} dB, mask IoU {iou:+.3f} "
                             f"(target >= +2 dB and > 0: {'met' if met else 'not met'})")
            if full and base and regime in THIRTY_IMAGES:
                gain = full["psnr"] - base["psnr"]
                lines.append(f"- {where}: {full_name} - sss3dgs = {gain:+.2f} dB (target >= +1 dB: "
                             f"{'met' if gain >= 1.0 else 'not met'})")
            dense = score.get((name, "lattice", "all", "dense"))
            if full and dense and form == "lattice" and regime in THIRTY_IMAGES:
                gap = full["psnr"] - dense["psnr"]
                lines.append(f"- {where}: {full_name} - dense = {gap:+.2f} dB (target >= -2 dB: "
                             f"{'met' if gap >= -2.0 else 'not met'})")
    return lines


def ceiling_lines(rows: list[dict], ceilings: dict[str, float | None]) -> list[str]:
    """Each object's noise ceiling and how far under it its dense row lies, as Markdown bullets."""
    dense = {r["object"]: r["psnr"] for r in rows if r["method"] == "dense"}
    return [f"- {name}: {ceiling:.2f} dB" + (f" (dense row {ceiling - dense[name]:.2f} dB under it)"
                                            if name in dense else "")
            for name, ceiling in ceilings.items() if ceiling is not None]


def markdown(rows: list[dict], iterations: int, note: str, ceilings: dict[str, float | None] | None = None) -> str:
    lines = [f"{iterations} steps per reconstruction (`short_schedule`), test split (novel views under novel lights). "
             "Pipeline rows: real images at least n / (n + "
             f"{PipelineConfig().generated_as_real:g}) of the images drawn for n real images unless named "
             f"`_shareN` (N%). {note}".strip(), "",
             ("| object | form | regime | stage | PSNR | SSIM | mask IoU | real / synthetic images | minutes "
             "(stages) |"),
             "|---|---|---|---|---|---|---|---|---|"]
    for r in [*rows, *mean_rows(rows)]:
        label = variant_label(r["method"])
        images = f"{r.get('real_images', '')} / {r['synthetic_images']:.0f}"
        minutes = "" if r.get("minutes") is None else f"{r['minutes']:.1f}"
        if r.get("stages"):
            minutes += " (" + ", ".join(f"{name} {seconds / 60:.1f}" for name, seconds in r["stages"].items()) + ")"
        lines.append(f"| {r['object']} | {r.get('form', 'lattice')} | `{r['regime']}` | {label} | {r['psnr']:.2f} | "
                     f"{r['ssim']:.4f} | {r['mask_iou']:.3f} | {images} | {minutes} |")
    ceilings_part = ["", "Noise ceilings (the test split rendered again with independent noise):",
                     *ceiling_lines(rows, ceilings)] if ceilings else []
    rounds = rounds_lines(rows)
    rounds_part = ["", "Test PSNR (mask IoU) after each round:", *rounds] if rounds else []
    return "\n".join([*lines, "", "Targets:", *target_lines([*rows, *mean_rows(rows)]), *rounds_part,
                      *ceilings_part]) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", nargs="+", default=list(DEFAULT_OBJECTS),
                        help="data folders or shape:material pairs")
    parser.add_argument("--regimes", nargs="+", default=list(REGIMES))
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--no-dense", action="store_true", help="skip the dense reference")
    parser.add_argument("--forms", nargs="+", default=["lattice"], choices=FORMS,
                        help="lattice: each regime drawn from the whole capture; sparse: the regime's images written "
                             "as a capture of their own first (what a user brings), every method on regime all")
    parser.add_argument("--iterations", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0, help="the regime's draw of views and lights and the training "
                                                            "seed (runs of a seed other than 0 go to <regime>_seed<N>)")
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--real-shares", nargs="+", type=share_value, default=[DEFAULT_SHARE],
                        help="the pipeline rows' min_real_share values (a lever): real images at least this share "
                             "of the images drawn; auto (default): n / (n + generated_as_real) for n real images")
    parser.add_argument("--agreement-powers", nargs="+", type=float, default=[DEFAULT_POWER],
                        help="the pipeline rows' agreement_power values (a lever): generated images that disagree "
                             "with the preliminary reconstruction more than the median lose weight")
    parser.add_argument("--pipeline-set", nargs="+", default=[], metavar="KEY=VALUE",
                        help="settings of the pipeline rows (needs --tag): PipelineConfig fields (e.g. "
                             "nvs_views=0) or training keys of the final reconstruction (e.g. hull_masks=real)")
    parser.add_argument("--tag", default="", help="suffix of the pipeline rows' names with --pipeline-set")
    parser.add_argument("--noise-ceilings", action="store_true",
                        help="report each rendered capture's noise ceiling (renders its test split again, once)")
    parser.add_argument("--note", default="", help="a line for the Markdown (machine, date)")
    parser.add_argument("--collect-only", action="store_true", help="report what the finished runs recorded (no training, no evaluation)")
    parser.add_argument("--out", type=Path, default=RUNS)
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    if bool(args.pipeline_set) != bool(args.tag):
        parser.error("--pipeline-set and --tag go together (the tag names the rows and folders of those settings)")
    pipeline_set = dict(item.split("=", 1) for item in args.pipeline_set)
    rows, finals, ceilings = [], {}, {}
    for spec in args.objects:
        data = resolve_object(spec, args.size, args.spp)
        if args.noise_ceilings:
            ceilings[data.name] = noise_ceiling_of(data, args.out / "noise_reference")
        pipeline_variants = [(share, power) for share in args.real_shares for power in args.agreement_powers]
        jobs = [(form, regime, method, share, power) for form in args.forms for regime in args.regimes
                for method in args.methods
                for share, power in (pipeline_variants if method in PIPELINE_METHODS
                                     else [(DEFAULT_SHARE, DEFAULT_POWER)])]
        jobs += [] if args.no_dense else [("lattice", "all", "dense", DEFAULT_SHARE, DEFAULT_POWER)]
        for form, regime, method, share, power in jobs:
            name = variant_name(method, share, power, args.tag)
            slug = regime_slug(regime) + ("_sparse" if form == "sparse" else "")
            runs = args.out / data.name / (slug + (f"_seed{args.seed}" if args.seed else ""))
            if args.collect_only:
                if (found := recorded(runs / name)) is None:
                    continue
                final, metrics = found
            elif form == "sparse":
                capture = sparse_capture(data, args.out, regime, args.seed)
                final, metrics = run_method(method, capture, runs, "all", args.iterations, share, power,
                                            pipeline_set, args.tag, args.seed)
            else:
                final, metrics = run_method(method, data, runs, regime, args.iterations, share, power,
                                            pipeline_set, args.tag, args.seed)
            rows.append({"object": data.name, "form": form, "regime": regime, "method": name, "run": str(runs / name),
                         "minutes": run_minutes(runs / name), "stages": stage_seconds(runs / name),
                         "rounds": round_metrics(runs / name),
                         **{k: metrics.get(k) for k in (*METRICS, "real_images", "synthetic_images", "real_share")}})
            finals[grid_key(rows[-1])] = final
            print(json.dumps(rows[-1]), flush=True)
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "regimes.json").write_text(json.dumps({"iterations": args.iterations, "note": args.note,
                                                           "rows": rows, "mean": mean_rows(rows),
                                                           "noise_ceilings": ceilings}, indent=2) + "\n")
    text = markdown(rows, args.iterations, args.note, ceilings)
    (args.results / "regimes.md").write_text(text)
    objects = [resolve_object(spec, args.size, args.spp) for spec in args.objects]
    save_regimes_grid(args.results / "regimes_grid.png", objects, finals, rows)
    print(text)


def grid_key(row: dict) -> tuple[str, str, str]:
    """A row's (object, regime, method) in the grid; the sparse form's regime is marked ``(sparse)``."""
    form = row.get("form", "lattice")
    return row["object"], f"{row['regime']} ({form})" if form == "sparse" else row["regime"], row["method"]


def short_regime(regime: str) -> str:
    """A grid label's regime: ``9`` / ``30`` for the paper's counts (as views x lights or images), then the form when
    sparse (``images=9 (sparse)`` -> ``9 sparse``); other regimes as they are."""
    base, _, form = regime.partition(" (")
    count = "9" if base in NINE_IMAGES else "30" if base in THIRTY_IMAGES else base
    return f"{count} {form.rstrip(')')}".strip()


def save_regimes_grid(path: Path, objects: list[Path], finals: dict[tuple[str, str, str], Path],
                      rows: list[dict]) -> Path:
    """One row per object: its test image 0 (view 0, light 0), then each reconstruction's render of it (``finals``,
    keyed by :func:`grid_key`), labelled with the regime, the method and its test PSNR (dB, the whole split)."""
    psnr = {grid_key(r): r["psnr"] for r in rows}
    grid, labels = [], []
    for data in objects:
        test = OLATDataset(data, "test")
        keys = [key for key in finals if key[0] == data.name]
        grid.append([to_display(test.load(0).rgb)] + [
            to_display(render_observation(load_scene(finals[key])[0], test, 0, "cpu").radiance[0]) for key in keys])
        labels.append(["ground truth", *[f"{short_regime(k[1])}: {k[2]} {psnr[k]:.2f}" for k in keys]])
    return save_image_grid(path, grid, row_labels=[data.name for data in objects], cell_labels=labels,
                           title="test view 0 under test light 0; test PSNR of the whole split")


if __name__ == "__main__":
    main()
