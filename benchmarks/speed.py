"""Speed of the reconstruction engine: deferred render (forward / backward) and full training steps.

Cases: Gaussian counts x square resolutions on an analytic sphere capture (CPU by default 1k/5k/20k x 64/128 px;
on CUDA, when present, 300k Gaussians at 800 px). For each case: the median time of a full deferred render
(SSS MLP + rasterization of the 14-channel G-buffer + GGX shading) forward and backward, and of a full training
step (batch 1, the `diamond` preset's objective) with and without the multi-view losses.
Prints a table, writes ``benchmarks/results/speed.json`` and ``speed.md``.

    python benchmarks/speed.py                      # CPU, ~2-4 min on 2 cores
    python benchmarks/speed.py --counts 5000 --resolutions 64 --repeats 10
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
from diamond_sss.training.config import make_config
from diamond_sss.training.trainer import ImageSource, Trainer

RESULTS = Path(__file__).resolve().parent / "results"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def time_case(root: Path, count: int, resolution: int, device: str, repeats: int, multiview: bool) -> dict:
    """Median render forward/backward and training-step times (ms) for one configuration."""
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
        forward, backward, steps = [], [], []
        cam = dataset.cameras[0]
        light = dataset.lights[0]
        args = (cam.w2c[None].to(dev), cam.K[None].to(dev), cam.width, cam.height, light.position[None].to(dev),
                light.intensity[None].to(dev))
        for k in range(repeats + 1):
            _sync(dev)
            start = time.perf_counter()
            render = scene.render(*args)
            _sync(dev)
            middle = time.perf_counter()
            render.radiance.sum().backward()
            _sync(dev)
            end = time.perf_counter()
            scene.zero_grad(set_to_none=True)
            trainer.training_step(scene, optimizers, state, k)
            _sync(dev)
            done = time.perf_counter()
            if k > 0:
                forward.append(1e3 * (middle - start))
                backward.append(1e3 * (end - middle))
                steps.append(1e3 * (done - end))
    return {"device": device, "gaussians": count, "resolution": resolution, "multiview": multiview,
            "render_forward_ms": statistics.median(forward), "render_backward_ms": statistics.median(backward),
            "train_step_ms": statistics.median(steps)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--counts", type=int, nargs="+", default=[1000, 5000, 20000])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--cuda-count", type=int, default=300_000)
    parser.add_argument("--cuda-resolution", type=int, default=800)
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cases = [("cpu", n, r) for r in args.resolutions for n in args.counts]
        if torch.cuda.is_available():
            cases.append(("cuda", args.cuda_count, args.cuda_resolution))
        else:
            print(f"CUDA case ({args.cuda_count} Gaussians, {args.cuda_resolution} px) skipped: no CUDA GPU")
        for device, count, resolution in cases:
            root = Path(tmp) / f"sphere_{resolution}"
            if not root.exists():
                make_capture(root, views=8, lights=4, size=resolution)
            for multiview in (False, True):
                rows.append(time_case(root, count, resolution, device, args.repeats, multiview))
                print(rows[-1], flush=True)
    header = "| device | Gaussians | px | multi-view losses | render fwd ms | render bwd ms | train step ms |"
    lines = [header, "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['device']} | {r['gaussians']} | {r['resolution']} | {'on' if r['multiview'] else 'off'} "
                     f"| {r['render_forward_ms']:.1f} | {r['render_backward_ms']:.1f} | {r['train_step_ms']:.1f} |")
    table = "\n".join(lines)
    print(table)
    meta = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "torch": torch.__version__,
            "threads": torch.get_num_threads(), "machine": platform.machine(), "processor": platform.processor(),
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "speed.json").write_text(json.dumps({"meta": meta, "results": rows}, indent=2) + "\n")
    (args.output / "speed.md").write_text(f"{json.dumps(meta)}\n\n{table}\n")


if __name__ == "__main__":
    main()
