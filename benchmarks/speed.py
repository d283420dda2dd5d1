"""Speed of the reconstruction engine: deferred render (forward / backward), training steps, scene set-up.

Cases: Gaussian counts x square resolutions on an analytic sphere capture. CPU: 1k/5k/20k x 64/128 px. CUDA
(``--device cuda``, or ``auto`` when a GPU is present): the issue's two targets, 10k Gaussians at 64 px and
300k at 800 px. For each case: the median time of a full deferred render (SSS MLP + rasterization of the
G-buffer + GGX shading) forward and backward, and the mean time of ``--steps`` consecutive training steps
(batch 1, the `diamond` preset's full objective: ray-traced visibility every ``raytrace_every`` steps
included) with and without the multi-view losses, timed with one device synchronisation at the end, as a
real run would see them. Also: the initial scales of a 1M-point cloud (``nearest_neighbor_scales``).
Prints a table, writes ``speed.json`` and ``speed.md`` under ``--output``.

    python benchmarks/speed.py                      # CPU, ~3-5 min on 2 cores
    python benchmarks/speed.py --device cuda        # the CUDA targets (needs gsplat's CUDA build)
    python benchmarks/speed.py --counts 5000 --resolutions 64 --repeats 10
    python benchmarks/speed.py --device cuda --profile   # + operators, kernels and host syncs per step, and where
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import torch

from diamond_sss.data.analytic import make_capture
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.gaussians.model import nearest_neighbor_scales
from diamond_sss.training.overrides import make_config
from diamond_sss.training.trainer import ImageSource, Trainer
from diamond_sss.utils.profiling import profile_steps, synchronize

RESULTS = Path(__file__).resolve().parent / "results"
PROFILE_STEPS = 5
"""Training steps profiled per case with ``--profile``."""


def time_case(root: Path, count: int, resolution: int, device: str, repeats: int, steps: int,
              multiview: bool, profile_dir: Path | None = None) -> dict:
    """Median render forward/backward (ms) and mean training-step time (ms) over ``steps`` steps; with
    ``profile_dir``, also :func:`profile_steps` of the 5 steps after them."""
    overrides = {"num_gaussians": count, "batch_size": 1, "densify": False, "lambda_lpips": 0.0, "device": device,
                 "log_every": 10_000, "init": "random"}
    if not multiview:
        overrides.update(lambda_sil=0.0, lambda_depth=0.0)
    cfg = make_config("diamond", overrides=overrides)
    dataset = OLATDataset(root)
    with tempfile.TemporaryDirectory() as run_dir:
        trainer = Trainer(cfg, [ImageSource(dataset)], Path(run_dir), show_progress=False)
        scene = trainer.build_scene()
        optimizers = trainer.build_optimizers(scene)
        state = trainer._initial_strategy_state()
        dev = trainer.device
        forward, backward = [], []
        cam = dataset.cameras[0]
        light = dataset.lights[0]
        args = (cam.w2c[None].to(dev), cam.K[None].to(dev), cam.width, cam.height, light.position[None].to(dev),
                light.intensity[None].to(dev))
        for k in range(repeats + 1):
            synchronize(dev)
            start = time.perf_counter()
            render = scene.render(*args)
            synchronize(dev)
            middle = time.perf_counter()
            render.radiance.sum().backward()
            synchronize(dev)
            end = time.perf_counter()
            scene.zero_grad(set_to_none=True)
            if k > 0:
                forward.append(1e3 * (middle - start))
                backward.append(1e3 * (end - middle))
        warmup = max(2, cfg.raytrace.every)
        for step in range(warmup):
            trainer.training_step(scene, optimizers, state, step)
        synchronize(dev)
        start = time.perf_counter()
        for step in range(warmup, warmup + steps):
            trainer.training_step(scene, optimizers, state, step)
        synchronize(dev)
        step_ms = 1e3 * (time.perf_counter() - start) / steps
        profiled = {}
        if profile_dir is not None:
            name = f"profile_{device}_{count}x{resolution}_{'mv' if multiview else 'plain'}.txt"
            profiled = profile_steps(lambda i: trainer.training_step(scene, optimizers, state, i), dev,
                                     warmup + steps, PROFILE_STEPS, profile_dir / name)
    return {"device": device, "gaussians": count, "resolution": resolution, "multiview": multiview,
            "render_forward_ms": statistics.median(forward), "render_backward_ms": statistics.median(backward),
            "train_step_ms": step_ms, "steps_per_second": 1e3 / step_ms, "steps": steps, **profiled}


def time_initial_scales(count: int) -> dict:
    """Seconds to compute the nearest-neighbour initial scales of ``count`` uniform random points (CPU)."""
    points = torch.rand(count, 3, generator=torch.Generator().manual_seed(0))
    start = time.perf_counter()
    nearest_neighbor_scales(points)
    return {"points": count, "seconds": time.perf_counter() - start}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                        help="cpu: the CPU grid; cuda: the CUDA cases; auto: both when a GPU is present")
    parser.add_argument("--counts", type=int, nargs="+", default=[1000, 5000, 20000])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--repeats", type=int, default=5, help="renders timed per case (median)")
    parser.add_argument("--steps", type=int, default=10, help="consecutive training steps timed per CPU case")
    parser.add_argument("--cuda-steps", type=int, default=200, help="consecutive training steps per CUDA case")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--cuda-cases", nargs="+", default=["10000x64", "300000x800"],
                        help="CUDA cases as GAUSSIANSxPIXELS")
    parser.add_argument("--scale-points", type=int, default=1_000_000, help="cloud size of the initial-scales row")
    parser.add_argument("--output", type=Path, default=RESULTS)
    parser.add_argument("--profile", action="store_true",
                        help="also profile 5 steps per case: operators, CUDA kernels and host syncs per step, and "
                             "where the time goes (profile_<case>.txt under --output)")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda but torch.cuda.is_available() is False")
    cases = []
    if args.device in ("auto", "cpu"):
        cases += [("cpu", n, r, args.steps) for r in args.resolutions for n in args.counts]
    if args.device == "cuda" or (args.device == "auto" and torch.cuda.is_available()):
        for case in args.cuda_cases:
            count, resolution = (int(v) for v in case.lower().split("x"))
            cases.append(("cuda", count, resolution, args.cuda_steps))
    elif args.device == "auto":
        print(f"CUDA cases ({', '.join(args.cuda_cases)}) skipped: no CUDA GPU")
    rows = []
    args.output.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for device, count, resolution, steps in cases:
            root = Path(tmp) / f"sphere_{resolution}"
            if not root.exists():
                make_capture(root, views=8, lights=4, size=resolution)
            for multiview in (False, True):
                rows.append(time_case(root, count, resolution, device, args.repeats, steps, multiview,
                                      args.output if args.profile else None))
                print(rows[-1], flush=True)
    scales = time_initial_scales(args.scale_points)
    print(scales, flush=True)
    header = ("| device | Gaussians | px | multi-view losses | render fwd ms | render bwd ms | train step ms "
              "| steps/s |")
    lines = [header, "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['device']} | {r['gaussians']} | {r['resolution']} | {'on' if r['multiview'] else 'off'} "
                     f"| {r['render_forward_ms']:.1f} | {r['render_backward_ms']:.1f} | {r['train_step_ms']:.1f} "
                     f"| {r['steps_per_second']:.1f} |")
    if args.profile:
        lines += ["", ("| device | Gaussians | px | multi-view losses | operators / step | CUDA kernels / step "
                       "| host syncs / step |"), "|---|---|---|---|---|---|---|"]
        lines += [f"| {r['device']} | {r['gaussians']} | {r['resolution']} | {'on' if r['multiview'] else 'off'} "
                  f"| {r['operators_per_step']:.0f} | {r['cuda_kernels_per_step']:.0f} | {r['host_syncs_per_step']:.1f} |"
                  for r in rows]
    lines.append("")
    lines.append(f"Initial scales (k-d tree, CPU) of {scales['points']:,} points: {scales['seconds']:.2f} s")
    for r in rows:
        if r["device"] == "cuda" and r["multiview"]:
            minutes = 30_000 * r["train_step_ms"] / 6e4
            lines.append(f"30,000 steps at {r['resolution']} px, {r['gaussians']:,} Gaussians: {minutes:.1f} min "
                         "(step time x 30k; image decoding of a real capture not included)")
    table = "\n".join(lines)
    print(table)
    meta = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "torch": torch.__version__,
            "threads": torch.get_num_threads(), "machine": platform.machine(), "processor": platform.processor(),
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
    (args.output / "speed.json").write_text(json.dumps({"meta": meta, "results": rows, "initial_scales": scales},
                                                       indent=2) + "\n")
    (args.output / "speed.md").write_text(f"{json.dumps(meta)}\n\n{table}\n")


if __name__ == "__main__":
    main()
