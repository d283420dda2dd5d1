"""Forward / backward speed of :func:`diamond_sss.rendering.rasterize`.

CPU: Gaussian counts x square resolutions (default 1k, 5k, 20k x 64, 128 px). CUDA (only when a GPU is
present): 300k Gaussians at 800 px. Prints a table and writes ``benchmarks/results/speed_raster.json``.

    python benchmarks/speed_raster.py                 # quick (< 2 min on a 2-core CPU)
    python benchmarks/speed_raster.py --repeats 10 --counts 1000 5000 20000 50000
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import time
from pathlib import Path

import torch

from diamond_sss.rendering import rasterize
from diamond_sss.utils.profiling import synchronize

RESULTS = Path(__file__).resolve().parent / "results" / "speed_raster.json"


def make_scene(n: int, resolution: int, channels: int, device: str, seed: int = 0):
    """``n`` random Gaussians filling a ball of radius 1, seen from distance 3 with a 40 degree field of view.

    Scales are set so that the Gaussians roughly tile the ball (mean scale ~ 0.6 n^(-1/3)), as after training.
    """
    g = torch.Generator().manual_seed(seed)
    direction = torch.randn(n, 3, generator=g)
    radius = torch.rand(n, 1, generator=g) ** (1 / 3)
    means = direction / direction.norm(dim=-1, keepdim=True) * radius
    quats = torch.randn(n, 4, generator=g)
    scales = (0.6 * n ** (-1 / 3)) * torch.exp(0.3 * torch.randn(n, 3, generator=g))
    opacities = torch.rand(n, generator=g) * 0.9 + 0.05
    features = torch.rand(n, channels, generator=g)
    viewmats = torch.eye(4)[None].clone()
    viewmats[0, 2, 3] = 3.0
    focal = 0.5 * resolution / math.tan(math.radians(20.0))
    Ks = torch.tensor([[focal, 0.0, resolution / 2], [0.0, focal, resolution / 2], [0.0, 0.0, 1.0]])[None]
    params = [t.to(device).requires_grad_(True) for t in (means, quats, scales, opacities, features)]
    return params, viewmats.to(device), Ks.to(device)


def time_case(n: int, resolution: int, channels: int, device: str, repeats: int, warmup: int) -> dict:
    """Median wall-clock forward and backward times (ms) of one configuration."""
    params, viewmats, Ks = make_scene(n, resolution, channels, device)
    forward, backward = [], []
    for step in range(warmup + repeats):
        synchronize(torch.device(device))
        start = time.perf_counter()
        out = rasterize(*params, viewmats, Ks, resolution, resolution)
        loss = out.features.square().mean() + out.depth.mean() + out.alpha.mean()
        synchronize(torch.device(device))
        middle = time.perf_counter()
        loss.backward()
        synchronize(torch.device(device))
        end = time.perf_counter()
        for p in params:
            p.grad = None
        if step >= warmup:
            forward.append(1e3 * (middle - start))
            backward.append(1e3 * (end - middle))
    return {
        "device": device,
        "gaussians": n,
        "resolution": resolution,
        "channels": channels,
        "forward_ms": statistics.median(forward),
        "backward_ms": statistics.median(backward),
        "mean_alpha": float(out.alpha.detach().mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--counts", type=int, nargs="+", default=[1000, 5000, 20000], help="CPU Gaussian counts"
    )
    parser.add_argument("--resolutions", type=int, nargs="+", default=[64, 128], help="CPU image sides (px)")
    parser.add_argument("--channels", type=int, default=8, help="feature channels")
    parser.add_argument("--repeats", type=int, default=3, help="timed repetitions (median is reported)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed repetitions first")
    parser.add_argument("--cuda-count", type=int, default=300_000, help="Gaussians in the CUDA case")
    parser.add_argument("--cuda-resolution", type=int, default=800, help="image side of the CUDA case (px)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--output", type=Path, default=RESULTS, help="JSON file for the results")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)

    rows = [
        time_case(n, res, args.channels, "cpu", args.repeats, args.warmup)
        for res in args.resolutions
        for n in args.counts
    ]
    if torch.cuda.is_available():
        rows.append(
            time_case(args.cuda_count, args.cuda_resolution, args.channels, "cuda", max(args.repeats, 10), 3)
        )
    else:
        print(f"CUDA case ({args.cuda_count} Gaussians, {args.cuda_resolution} px) skipped: no CUDA GPU")

    print(f"{'device':>6} {'gaussians':>9} {'res':>5} {'C':>3} {'fwd ms':>8} {'bwd ms':>8} {'alpha':>6}")
    for r in rows:
        print(
            f"{r['device']:>6} {r['gaussians']:>9} {r['resolution']:>5} {r['channels']:>3} "
            f"{r['forward_ms']:>8.1f} {r['backward_ms']:>8.1f} {r['mean_alpha']:>6.2f}"
        )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
        "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }
    args.output.write_text(json.dumps({"meta": meta, "results": rows}, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
