"""Speed of the reconstruction engine: deferred render (forward / backward), training steps, scene set-up.

Cases: Gaussian counts x square resolutions on an analytic sphere capture. CPU: 1k/5k/20k x 64/128 px. CUDA
(``--device cuda``, or ``auto`` when a GPU is present): the issue's two targets, 10k Gaussians at 64 px and
300k at 800 px. For each case: the median time of a full deferred render (SSS MLP + rasterization of the
G-buffer + GGX shading) forward and backward, and the mean time of ``--steps`` consecutive training steps
(batch 1, the `diamond` preset's full objective: ray-traced visibility every ``raytrace_every`` steps
included) with and without the multi-view losses, timed with one device synchronisation at the end, as a
real run would see them. Every step row also gives what torch.profiler counts over 5 more steps: the top-level
aten operators dispatched per step (on any device: the proxy of the step's launches between GPU leases) and on CUDA
the kernels launched and the host syncs per step, and the peak GPU memory of the steps. On CUDA each case
also times the plain 3DGS step at the same Gaussians and image size (gsplat's RGB rasterization, 0.8 L1 + 0.2
D-SSIM, Adam, no densification: :func:`time_plain_3dgs`), the floor a step of this method is compared to
(``x plain 3DGS``: its step time over that one); on CPU that row says it needs CUDA. Also: the initial scales of a
1M-point cloud (``nearest_neighbor_scales``). Prints a table, writes ``speed.json`` (the method's rows under
``results``, the plain 3DGS rows under ``plain_3dgs``) and ``speed.md`` under ``--output``.

    python benchmarks/speed.py                      # CPU, ~3-5 min on 2 cores
    python benchmarks/speed.py --device cuda        # the CUDA targets (needs gsplat's CUDA build)
    python benchmarks/speed.py --counts 10000 --resolutions 64 --steps 3   # the small case's operator counts
    python benchmarks/speed.py --device cuda --profile   # + where the time goes (profile_<case>.txt)
    python benchmarks/speed.py --device cuda --compile off inductor   # + the step under runtime.compile=inductor
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
from diamond_sss.losses.photometric import photometric_loss
from diamond_sss.training.overrides import make_config
from diamond_sss.training.trainer import ImageSource, Trainer
from diamond_sss.utils.compiling import COMPILE_BACKENDS
from diamond_sss.utils.profiling import profile_steps, synchronize

RESULTS = Path(__file__).resolve().parent / "results"
PROFILE_STEPS = 5
"""Plain 3DGS steps profiled per case (operators, kernels and host syncs per step); the method's steps are profiled
over one period of its ray-traced visibility (``raytrace.every``, 10), which one of them includes."""

PLAIN_3DGS_LR = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "colors": 2.5e-3}
"""The learning rates of 3DGS (gsplat's ``simple_trainer``): the means' times the scene radius, the colours' that of
its SH band 0."""

PLAIN_3DGS_DSSIM = 0.2
"""3DGS's loss: ``(1 - 0.2) L1 + 0.2 D-SSIM``."""


def gpu_mib(device: torch.device, peak: bool = False) -> float | None:
    """GPU memory allocated on ``device`` now, or with ``peak`` its peak since the last
    ``torch.cuda.reset_peak_memory_stats`` (MiB); ``None`` off CUDA."""
    if device.type != "cuda":
        return None
    return (torch.cuda.max_memory_allocated(device) if peak else torch.cuda.memory_allocated(device)) / 2**20


def time_steps(step, device: torch.device, first: int, steps: int, profiled: int, profile_path: Path) -> dict:
    """Mean wall time (ms) of ``step(i)`` for ``i`` in ``[first, first + steps)`` (one device synchronisation at the
    end), the peak GPU memory over them (MiB, CUDA) and :func:`profile_steps` of the ``profiled`` steps after them
    (tables in ``profile_path``). ``peak_gpu_mib``: the peak of the memory allocated during the steps, ``step_gpu_mib``:
    that peak less what was allocated before them (what a step adds to the resident scene, data and optimizer state:
    activations, gradients, temporaries)."""
    synchronize(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    resident = gpu_mib(device)
    start = time.perf_counter()
    for i in range(first, first + steps):
        step(i)
    synchronize(device)
    step_ms = 1e3 * (time.perf_counter() - start) / steps
    peak = gpu_mib(device, peak=True)
    counts = profile_steps(step, device, first + steps, profiled, profile_path)
    return {"train_step_ms": step_ms, "steps_per_second": 1e3 / step_ms, "steps": steps, "peak_gpu_mib": peak,
            "step_gpu_mib": None if peak is None else peak - resident, "profiled_steps": profiled, **counts}


def time_plain_3dgs(scene, dataset: OLATDataset, device: torch.device, steps: int, profile_path: Path) -> dict:
    """The plain 3DGS training step at ``scene``'s Gaussians and ``dataset``'s image size: ``gsplat.rasterization``
    of RGB colours (``sigmoid`` of the base colour; no SH, G-buffer, MLP or shading), ``(1 - 0.2) L1 + 0.2 D-SSIM``
    (:func:`photometric_loss`), Adam at :data:`PLAIN_3DGS_LR` (``eps = 1e-15``, as 3DGS), batch 1, no densification.
    :func:`time_steps` after a warm-up of 10 steps. CUDA only (gsplat)."""
    from gsplat import rasterization

    raw = scene.gaussians.params
    names = {"means": "means", "scales": "scales", "quats": "quats", "opacities": "opacities", "colors": "base_color"}
    params = {name: raw[source].detach().clone().requires_grad_(True) for name, source in names.items()}
    radius = dataset.bounds.radius
    optimizer = torch.optim.Adam([{"params": [value], "lr": PLAIN_3DGS_LR[name] * (radius if name == "means" else 1.0)}
                                  for name, value in params.items()], eps=1e-15)
    views = []
    for index in range(len(dataset)):
        sample = dataset.load(index)
        camera = dataset.cameras[sample.view]
        views.append((camera.w2c[None].to(device), camera.K[None].to(device), sample.rgb[None].to(device)))
    width, height = dataset.cameras[0].width, dataset.cameras[0].height

    def step(i: int) -> None:
        w2c, K, target = views[i % len(views)]
        rgb, _, _ = rasterization(params["means"], params["quats"], torch.exp(params["scales"]),
                                  torch.sigmoid(params["opacities"]), torch.sigmoid(params["colors"]), w2c, K, width,
                                  height)
        photometric_loss(rgb, target, PLAIN_3DGS_DSSIM).backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)

    for i in range(10):
        step(i)
    return {"device": device.type, "gaussians": scene.gaussians.num_gaussians, "resolution": width,
            **time_steps(step, device, 10, steps, PROFILE_STEPS, profile_path)}


def time_case(root: Path, count: int, resolution: int, device: str, repeats: int, steps: int,
              multiview: bool, profile_dir: Path, plain_3dgs: bool = False,
              compile_backend: str = "off") -> tuple[dict, dict | None]:
    """Median render forward/backward (ms) and :func:`time_steps` of ``steps`` training steps (the tables of the
    profiled steps in ``profile_dir``) under ``runtime.compile = compile_backend`` (``warmup_s``: the steps before
    the timed ones, compilation included); with ``plain_3dgs``, also :func:`time_plain_3dgs` at the same Gaussians
    and size (else ``None``)."""
    overrides = {"num_gaussians": count, "batch_size": 1, "densify": False, "lambda_lpips": 0.0, "device": device,
                 "log_every": 10_000, "init": "random", "compile": compile_backend}
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
        name = f"profile_{device}_{count}x{resolution}"
        plain = time_plain_3dgs(scene, dataset, dev, steps, profile_dir / f"{name}_3dgs.txt") if plain_3dgs else None
        warmup = max(2, cfg.raytrace.every)
        started = time.perf_counter()
        for step in range(warmup):
            trainer.training_step(scene, optimizers, state, step)
        synchronize(dev)
        warmup_s = time.perf_counter() - started
        suffix = ("mv" if multiview else "no_mv") + ("" if compile_backend == "off" else f"_{compile_backend}")
        timed = time_steps(lambda i: trainer.training_step(scene, optimizers, state, i), dev, warmup, steps,
                           max(PROFILE_STEPS, cfg.raytrace.every), profile_dir / f"{name}_{suffix}.txt")
    row = {"device": device, "gaussians": count, "resolution": resolution, "multiview": multiview,
           "compile": compile_backend, "warmup_s": warmup_s,
           "render_forward_ms": statistics.median(forward), "render_backward_ms": statistics.median(backward), **timed}
    return row, plain


def time_initial_scales(count: int) -> dict:
    """Seconds to compute the nearest-neighbour initial scales of ``count`` uniform random points (CPU)."""
    points = torch.rand(count, 3, generator=torch.Generator().manual_seed(0))
    start = time.perf_counter()
    nearest_neighbor_scales(points)
    return {"points": count, "seconds": time.perf_counter() - start}


def _number(value: float | None, digits: int = 1) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def _cells(r: dict) -> str:
    """The cells a step row shares with the plain 3DGS row: step time and rate, the profiled counts per step (kernels
    and host syncs on CUDA only), the peak GPU memory and what of it the step adds (:func:`time_steps`)."""
    cuda = r["device"] == "cuda"
    return (f"| {r['train_step_ms']:.2f} | {r['steps_per_second']:.1f} | {_number(r.get('x_plain_3dgs'), 2)} "
            f"| {r['operators_per_step']:.0f} | {_number(r['cuda_kernels_per_step'] if cuda else None, 0)} "
            f"| {_number(r['host_syncs_per_step'] if cuda else None)} | {_number(r['peak_gpu_mib'])} "
            f"| {_number(r['step_gpu_mib'])} |")


def table_lines(rows: list[dict], plain: list[dict]) -> list[str]:
    """The markdown table: per case the plain 3DGS step (or why it is missing) and the method's two steps, each with
    its time, its ratio to the plain step, what the profiler counted and the peak GPU memory."""
    lines = [("| device | Gaussians | px | step | render fwd ms | render bwd ms | train step ms | steps/s "
              "| x plain 3DGS | aten ops / step | CUDA kernels / step | host syncs / step | peak GPU MiB "
              "| step GPU MiB |"),
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for case in dict.fromkeys((r["device"], r["gaussians"], r["resolution"]) for r in rows):
        head = "| {} | {} | {} ".format(*case)
        base = [b for b in plain if (b["device"], b["gaussians"], b["resolution"]) == case]
        lines.append(head + ("| plain 3DGS (gsplat) | | " + _cells({**base[0], "x_plain_3dgs": 1.0}) if base
                             else "| plain 3DGS (gsplat) | | | needs CUDA | | | | | | | |"))
        lines += [head + f"| full objective, multi-view losses {'on' if r['multiview'] else 'off'}"
                  + ("" if r.get("compile", "off") == "off" else f", compiled ({r['compile']})") + " "
                  f"| {r['render_forward_ms']:.1f} | {r['render_backward_ms']:.1f} " + _cells(r)
                  for r in rows if (r["device"], r["gaussians"], r["resolution"]) == case]
    return lines


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
    parser.add_argument("--compile", nargs="+", default=["off"], choices=COMPILE_BACKENDS,
                        help="runtime.compile values, each a row per case (e.g. off inductor)")
    parser.add_argument("--profile", action="store_true",
                        help="also write where the time of the 5 profiled steps per case goes (profile_<case>.txt "
                             "under --output; the counts per step are in every row either way)")
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
    rows, plain = [], []
    args.output.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        profile_dir = args.output if args.profile else Path(tmp) / "profiles"
        for device, count, resolution, steps in cases:
            root = Path(tmp) / f"sphere_{resolution}"
            if not root.exists():
                make_capture(root, views=8, lights=4, size=resolution)
            for backend, multiview in ((b, m) for b in args.compile for m in (False, True)):
                first = backend == args.compile[0] and not multiview
                row, base = time_case(root, count, resolution, device, args.repeats, steps, multiview, profile_dir,
                                      plain_3dgs=device == "cuda" and first, compile_backend=backend)
                if base is not None:
                    plain.append(base)
                    print(base, flush=True)
                matching = [b for b in plain if (b["gaussians"], b["resolution"], b["device"]) ==
                            (count, resolution, device)]
                row["x_plain_3dgs"] = row["train_step_ms"] / matching[0]["train_step_ms"] if matching else None
                rows.append(row)
                print(rows[-1], flush=True)
    scales = time_initial_scales(args.scale_points)
    print(scales, flush=True)
    lines = table_lines(rows, plain)
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
    (args.output / "speed.json").write_text(json.dumps({"meta": meta, "results": rows, "plain_3dgs": plain,
                                                        "initial_scales": scales}, indent=2) + "\n")
    (args.output / "speed.md").write_text(f"{json.dumps(meta)}\n\n{table}\n")


if __name__ == "__main__":
    main()
