"""The diffusion stages of a sparse pipeline timed alone and beside a training run (issue 60).

For each --threads value (the pipeline's `generation_threads`: `auto`, its default, the cores other processes leave
idle when a stage starts; 0: torch's default, all cores; N: N threads) and each condition (`alone`; `beside`: a
1-thread `diamond-sss train` process on the same capture meanwhile), the novel-view and the relighting stage of
`diamond-sss run` (`pipeline.run.nvs_stage`, `relight_stage`, the silhouette filter between them, each on its
threads as the pipeline runs it, `pipeline.run.threaded`) generate into a fresh cache and are timed. The
preliminary reconstruction is --prelim-run, a finished run on the capture and regime, or is trained once into
--work (`sss3dgs`, the short schedule). Targets: both stages <= 30 s on the 2-core
CPU alone and <= 2x that beside a training run; <= 5 s on a GPU, never slower than on the CPU.

    python benchmarks/generation_speed.py --threads auto 0 1 --beside-training      # the demo object, 9 images
    python benchmarks/generation_speed.py --data CAPTURE --regime all --prelim-run RUN
    python benchmarks/generation_speed.py --device cuda --threads 0     # the stages on a GPU

Writes generation_speed.json and generation_speed.md to --results.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.pipeline.run import (
    PipelineConfig,
    SilhouetteFilter,
    checked_config,
    nvs_images,
    nvs_stage,
    prepare_run,
    relight_stage,
    threaded,
    write_relight_sources,
)
from diamond_sss.training.config import short_schedule
from diamond_sss.training.run import train_from_preset

RESULTS = Path(__file__).resolve().parent / "results" / "generation_speed"
WORK = Path("outputs") / "benchmarks" / "generation_speed"
HEADER = "| threads | condition | novel views (s) | relighting (s) | both (s) | generated images |"


@contextmanager
def beside(command: list[str] | None) -> Iterator[None]:
    """``command`` running as a separate process inside the block (stopped after it); ``None``: nothing."""
    if command is None:
        yield
        return
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(2.0)  # past its imports: the timing sees it training
        yield
    finally:
        process.terminate()
        process.wait()


def training_command(data: Path, out: Path) -> list[str]:
    """A 1-thread `diamond-sss train` of ``data`` into ``out``, long enough to outlast the timing."""
    return [sys.executable, "-m", "diamond_sss.cli.main", "train", "--data", str(data), "--out", str(out),
            "--iterations", "100000", "--quiet", "--set", "cpu_threads=1"]


def time_stages(data: Path, regime: str, prelim_run: Path, work: Path, config: PipelineConfig) -> dict:
    """Seconds of the novel-view and relighting stages into a fresh ``work`` folder and cache, and their images."""
    shutil.rmtree(work, ignore_errors=True)
    cfg = checked_config(replace(config, prelim_run=str(prelim_run), cache_dir=str(work / "cache")))
    ctx, _ = prepare_run(data, work / "out", split="train", regime=regime, preset="diamond",
                         overrides=short_schedule(1000, pipeline_final=True), seed=0, cfg=cfg, show_progress=False)
    started = time.perf_counter()
    nvs = threaded(cfg, "novel views", lambda: nvs_stage(ctx))
    between = time.perf_counter()
    kept = SilhouetteFilter(ctx).keep(nvs_images(ctx))
    sources = write_relight_sources(ctx, kept)
    relight = threaded(cfg, "relighting", lambda: relight_stage(ctx, sources))
    ended = time.perf_counter()
    return {"nvs_s": between - started, "relight_s": ended - between, "both_s": ended - started,
            "images": len(kept) + relight["images"], "nvs_calls": nvs.get("calls", 0), "relit": relight["images"]}


def threads_value(text: str) -> int | None:
    """A --threads value: ``auto`` (``None``, the pipeline's default) or a count >= 0."""
    if text == "auto":
        return None
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"--threads takes auto or a count >= 0 (0: torch's default), got {text!r}")
    return int(text)


def run(data: Path, regime: str, prelim_run: Path | None, work: Path, results: Path, threads: list[int | None],
        conditions: list[str], config: PipelineConfig | None = None) -> list[dict]:
    """Every (threads, condition) row, written to ``results`` as JSON and Markdown; ``config``: the pipeline's
    settings (default: its defaults, the shipped models)."""
    if any(count is not None and count < 0 for count in threads):
        raise ValueError(f"--threads must be auto or >= 0 (0: torch's default), got {threads}")
    config = checked_config(config)  # a bad --device stops here, before the preliminary reconstruction trains
    if prelim_run is None:
        prelim_run = work / "prelim"
        train_from_preset(data, prelim_run, preset="sss3dgs", overrides=short_schedule(1000), regime=regime,
                          resume=True, show_progress=False)
    rows = []
    for count in threads:
        for condition in conditions:
            command = training_command(data, work / "background") if condition == "beside" else None
            with beside(command):
                row = time_stages(data, regime, prelim_run, work / "stages",
                                  replace(config, generation_threads=count))
            rows.append({"threads": count, "condition": condition, **row})
            print(json.dumps(rows[-1]), flush=True)
    results.mkdir(parents=True, exist_ok=True)
    device = config.device
    meta = {"data": str(data), "regime": regime, "prelim_run": str(prelim_run), "device": device}
    (results / "generation_speed.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    lines = [f"Diffusion stages of `diamond-sss run` on {data} (`{regime}`), device {device}, fresh cache.", "",
             HEADER,
             "|---|---|---|---|---|---|"]
    named = {None: "auto", 0: "default"}
    lines += [f"| {named.get(r['threads'], r['threads'])} | {r['condition']} | {r['nvs_s']:.1f} | "
              f"{r['relight_s']:.1f} | {r['both_s']:.1f} | {r['images']} |" for r in rows]
    (results / "generation_speed.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=None, help="a capture (default: the embedded demo object)")
    parser.add_argument("--regime", default="views=3,lights=3")
    parser.add_argument("--prelim-run", type=Path, default=None,
                        help="a finished reconstruction of the regime's images (default: trained into --work)")
    parser.add_argument("--threads", nargs="+", type=threads_value, default=[None, 0, 1])
    parser.add_argument("--beside-training", action="store_true", help="also time beside a 1-thread training run")
    parser.add_argument("--work", type=Path, default=WORK)
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--device", default="auto", help="the diffusion models' device (pipeline --device)")
    args = parser.parse_args()
    conditions = ["alone", "beside"] if args.beside_training else ["alone"]
    try:
        run(args.data or embedded_dataset(), args.regime, args.prelim_run, args.work, args.results, args.threads,
            conditions, PipelineConfig(device=args.device))
    except ValueError as exc:
        sys.exit(f"generation_speed: {exc}")


if __name__ == "__main__":
    main()
