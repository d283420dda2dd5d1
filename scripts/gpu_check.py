"""Everything that needs a CUDA GPU, in one command, with one report (``make gpu-check``).

Steps, each timed and recorded even when an earlier one failed:
  1. the machine: GPU, driver, CUDA, torch, gsplat, Python;
  2. gsplat's CUDA build (JIT, first use) with one tiny ``gsplat.rasterization`` call;
  3. the CUDA tests (``pytest -m cuda``), then the whole suite on the CUDA machine;
  4. ``benchmarks/speed.py --device cuda`` (training-step targets), the same under ``runtime.compile=inductor``
     (``speed-compiled``), the diffusion stages of a 9-image pipeline on the GPU (``generation``:
     ``benchmarks/generation_speed.py --device cuda``) and ``benchmarks/speed_raster.py``; then
     ``benchmarks/nvs_speed.py`` on the GPU prior's model (below): its step in parts, 4 and 8 objects, fp32 and
     bf16, deterministic and autotuned kernels, profiled;
  5. a demo-object reconstruction on CUDA (`diamond` preset, full objective) and its evaluation on the test
     split (novel views under novel lights);
  6. with ``--prior-data``: a larger, 64-px novel-view prior (issue 18's 30-image lever) trained for
     ``--prior-minutes`` of wall time on those captures (``scripts/make_prior_data.sh`` renders them on a CPU
     machine; it also packs them into ``outputs/priors.tgz``, 10 MB, the form to carry to a lent GPU machine and
     unpack there: ``scripts/gpu_lease.sh`` does it); the run stops checkpointed at its time limit
     and its EMA weights are written in fp16 to ``<out>/nvs_prior_model`` (12 MiB), for the CPU rows of
     ``benchmarks/regimes.py --pipeline-set nvs_model=...``; float32 by default (``--prior-precision``: bf16
     autocast took 1.5x as long per step under the deterministic kernels, H200, 2026-11-27),
     and ``--prior-init`` goes on from an earlier lease's prior (fresh optimiser and warm-up), so that 15-minute
     leases add up.
Writes ``report.json`` and ``report.md`` (plus each step's log) under ``--out``.

    python scripts/gpu_check.py --out gpu_check            # ~10-15 min on an H100
    python scripts/gpu_check.py --skip suite --iterations 1000
    python scripts/gpu_check.py --skip cuda-tests suite speed speed-raster --iterations 10000 \
        --set lr.decay_step=7000 --set lr.decay_factor=0.3 --set sss_angular_inputs=true \
        --set sss_light_depth=64   # issue 17's 10k run (the short-run settings)
    python scripts/gpu_check.py --skip build cuda-tests suite speed speed-raster train eval \
        --prior-data outputs/priors/* --prior-minutes 7   # issue 18's novel-view prior
    ... --prior-init <an earlier lease's nvs_prior_model> # the prior trained on from where it stopped
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STEPS = ("build", "cuda-tests", "suite", "speed", "speed-compiled", "generation", "speed-raster", "nvs-speed", "train",
         "eval", "nvs-prior")
PRIOR_MODEL = ["--image-size", "64", "--block-out-channels", "48", "96", "96", "--layers-per-block", "2",
               "--prediction-type", "v_prediction", "--hint-residual", "--no-gradient-checkpointing",
               "--learning-rate", "3e-4", "--objects-per-batch", "8", "--checkpoint-every", "500", "--log-every", "20"]
"""``finetune-nvs`` options of the GPU prior: 6.4 M parameters (3.2x the shipped model's), 64 px, the shipped recipe
but 8 objects (32 target views) per step, not 4: at 64 px a step of this model should be kernel launches more than
arithmetic on an H100/H200 (~1 TFLOP per 16 views; session 17 measured 0.16 s per step in fp32), so twice the batch
should cost little time (unmeasured: the report gives the seconds per step)."""
DEPTH_NOISE_FLAGS = ("depth-noise-share", "depth-noise-relative", "depth-noise-edge-px")
"""``finetune-nvs`` flags that ``--prior-depth-noise`` sets, in its order."""
PRIOR_MAX_STEPS = 1_000_000
"""Never reached: the prior's run ends at its time limit (the learning rate is constant after the warm-up)."""
PRIOR_GRACE_S = 300
"""Seconds beyond its time limit before the prior's run is killed: loading the captures, the last checkpoint."""


def run_step(name: str, command: list[str], out: Path, timeout: int, env: dict[str, str]) -> dict:
    """Run ``command``, log its output to ``out/<name>.log``; return status, seconds and the log's tail."""
    start = time.perf_counter()
    log_path = out / f"{name}.log"
    print(f"[gpu-check] {name}: {' '.join(command)}", flush=True)
    try:
        proc = subprocess.run(command, check=False, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
        output, code = proc.stdout + proc.stderr, proc.returncode
    except subprocess.TimeoutExpired as exc:
        output = (exc.stdout or b"").decode(errors="replace") if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        output += f"\n[gpu-check] timed out after {timeout} s"
        code = 124
    log_path.write_text(output)
    seconds = time.perf_counter() - start
    print(f"[gpu-check] {name}: exit {code} in {seconds:.0f} s (log: {log_path})", flush=True)
    return {"step": name, "exit_code": code, "seconds": round(seconds, 1), "log": log_path.name,
            "tail": output.strip().splitlines()[-15:]}


def run_nvs_prior(cli: list[str], data: list[Path], minutes: float, out: Path, env: dict[str, str],
                  precision: str = "no", init: Path | None = None, depth_noise: list[float] | None = None) -> dict:
    """Train the GPU prior for ``minutes`` of wall time (``finetune-nvs --time-limit-s``: it stops checkpointed at
    the first step past it) in ``precision`` (autocast), from ``init``'s weights when given (an earlier lease's
    prior, carried back), with the reference depth perturbed as ``depth_noise`` = (share, relative, edge_px) says
    when given, and export its EMA weights in fp16 to ``out/nvs_prior_model``."""
    run = out / "nvs_prior_run"
    noise = [] if depth_noise is None else [
        f"--{flag}={value:g}" for flag, value in zip(DEPTH_NOISE_FLAGS, depth_noise, strict=True)]
    command = cli + ["finetune-nvs", "--out", str(run), "--data", *map(str, data), *PRIOR_MODEL,
                     "--steps", str(PRIOR_MAX_STEPS), "--time-limit-s", f"{minutes * 60:g}",
                     "--mixed-precision", precision, *(["--init-from", str(init)] if init else []), *noise]
    result = run_step("nvs-prior", command, out, int(minutes * 60) + PRIOR_GRACE_S, env)
    if (last := last_log_record(run / "train_log.jsonl")) is not None:
        result["summary"] = (f"{last['step']} steps, loss {last['loss']:.4f}, {last['seconds']:.3f} s at the last "
                             f"logged step ({'float32' if precision == 'no' else precision}"
                             f"{', from ' + str(init) if init else ''})")
    if result["exit_code"] == 0:
        from diamond_sss.diffusion.nvs.model import NVSModel

        NVSModel.load(run / "model").save(out / "nvs_prior_model", half=True)
        result["tail"].append(f"fp16 model -> {out / 'nvs_prior_model'}")
    return result


def last_log_record(path: Path) -> dict | None:
    """The last complete record of a JSON-lines log (a line cut short by a killed run is skipped), or None."""
    if not path.is_file():
        return None
    for line in reversed(path.read_text(errors="replace").splitlines()):
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(record, dict) and {"step", "loss", "seconds"} <= record.keys():
            return record
    return None


def pytest_counts(lines: list[str]) -> str:
    """pytest's closing line (``N passed, M failed ...``) from a log tail, or ''."""
    for line in reversed(lines):
        if re.search(r"\d+ (passed|failed|error)", line):
            return line.strip("= ")
    return ""


def machine_facts() -> dict:
    import torch

    facts = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "python": platform.python_version(),
             "torch": torch.__version__, "cuda_runtime": torch.version.cuda, "cuda_available": torch.cuda.is_available(),
             "cpu_count": os.cpu_count()}
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        facts.update(gpu=props.name, gpu_memory_gib=round(props.total_memory / 2**30, 1),
                     compute_capability=f"{props.major}.{props.minor}")
    try:
        import gsplat

        facts["gsplat"] = gsplat.__version__
    except ImportError:
        facts["gsplat"] = None
    try:
        query = ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"]
        facts["driver"] = subprocess.run(query, check=False, capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        facts["driver"] = None
    return facts


BUILD = """
import torch, gsplat
means = torch.zeros(1, 3, device="cuda"); means[:, 2] = 2.0
quats = torch.tensor([[1.0, 0, 0, 0]], device="cuda"); scales = torch.full((1, 3), 0.1, device="cuda")
K = torch.tensor([[[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]]], device="cuda")
colors, alphas, _ = gsplat.rasterization(means, quats, scales, torch.ones(1, device="cuda"),
                                         torch.ones(1, 3, device="cuda"), torch.eye(4, device="cuda")[None], K, 16, 16)
torch.cuda.synchronize(); print("gsplat CUDA build ok, centre alpha", float(alphas[0, 8, 8, 0]))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "gpu_check")
    parser.add_argument("--skip", nargs="*", default=[], choices=STEPS, help="steps to leave out")
    parser.add_argument("--iterations", type=int, default=3000, help="steps of the demo-object reconstruction")
    parser.add_argument("--timeout", type=int, default=1800, help="seconds per step at most")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="config key of the demo-object reconstruction, as `diamond-sss train --set` (repeatable)")
    parser.add_argument("--prior-data", type=Path, nargs="*", default=[],
                        help="captures the novel-view prior trains on (scripts/make_prior_data.sh); none: no prior")
    parser.add_argument("--prior-minutes", type=float, default=7.0, help="training time of the novel-view prior")
    parser.add_argument("--prior-precision", default="no", choices=("no", "bf16", "fp16"),
                        help="autocast of the prior's training (finetune-nvs --mixed-precision)")
    parser.add_argument("--prior-init", type=Path, default=None,
                        help="model folder the prior starts from (an earlier run's nvs_prior_model): its training "
                             "goes on across leases")
    parser.add_argument("--prior-depth-noise", type=float, nargs=3, default=None,
                        metavar=("SHARE", "RELATIVE", "EDGE_PX"),
                        help="train the prior on reference depth perturbed like a sparse reconstruction's render "
                             "(finetune-nvs --depth-noise-*; benchmarks/sparse_depth.py calibrates them)")
    args = parser.parse_args()
    import torch

    if not 0 < args.prior_minutes < float("inf"):
        parser.error(f"--prior-minutes must be a positive number of minutes, got {args.prior_minutes}")
    missing = [str(path) for path in args.prior_data if not (path / "meta.json").is_file()]
    if missing:
        parser.error(f"--prior-data: not a finished capture (no meta.json): {', '.join(missing)}")
    if args.prior_init is not None and not (args.prior_init / "config.json").is_file():
        parser.error(f"--prior-init: {args.prior_init} is not a model folder (no config.json)")
    if not torch.cuda.is_available():
        parser.error("no CUDA GPU (torch.cuda.is_available() is False): this check is for a CUDA machine")
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    major, minor = torch.cuda.get_device_capability(0)
    env.setdefault("TORCH_CUDA_ARCH_LIST", f"{major}.{minor}")
    env.setdefault("MAX_JOBS", str(os.cpu_count() or 4))
    env.setdefault("TORCH_EXTENSIONS_DIR", str(Path.home() / ".cache" / "torch_extensions"))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT / "src"), env.get("PYTHONPATH")]))
    env.setdefault("HF_HUB_OFFLINE", "1")
    env["PYTHONUNBUFFERED"] = "1"
    python = sys.executable
    run_dir = out / "demo_run"
    from diamond_sss.data.embedded import embedded_dataset

    demo = embedded_dataset()
    cli = [python, "-m", "diamond_sss.cli.main"]
    commands = {
        "build": [python, "-c", BUILD],
        "cuda-tests": [python, "-m", "pytest", "-q", "-m", "cuda", "-p", "no:cacheprovider"],
        "suite": [python, "-m", "pytest", "-q", "-p", "no:cacheprovider"],
        "speed": [python, "benchmarks/speed.py", "--device", "cuda", "--profile", "--output", str(out)],
        "speed-compiled": [python, "benchmarks/speed.py", "--device", "cuda", "--compile", "inductor", "--profile",
                           "--output", str(out / "speed_compiled")],
        "generation": [python, "benchmarks/generation_speed.py", "--device", "cuda", "--threads", "0",
                       "--work", str(out / "generation_work"), "--results", str(out / "generation_speed")],
        "speed-raster": [python, "benchmarks/speed_raster.py", "--resolutions", "64", "--counts", "10000",
                         "--output", str(out / "speed_raster.json")],
        "nvs-speed": [python, "benchmarks/nvs_speed.py", *(["--data", *map(str, args.prior_data)] if args.prior_data
                                                           else []), *PRIOR_MODEL, "--profile",
                      "--output", str(out / "nvs_speed")],
        "train": cli + ["train", "--data", str(demo), "--out", str(run_dir), "--preset", "diamond",
                        "--iterations", str(args.iterations), "--device", "cuda", "--quiet",
                        *(f"--set={item}" for item in args.set)],
        "eval": cli + ["eval", "--run", str(run_dir), "--data", str(demo), "--split", "test", "--json",
                       "--device", "cuda"],
    }
    report = {"machine": machine_facts(), "steps": []}
    for name in STEPS:
        if name in args.skip or (name == "nvs-prior" and not args.prior_data):
            continue
        if name == "nvs-prior":
            result = run_nvs_prior(cli, args.prior_data, args.prior_minutes, out, env, args.prior_precision,
                                   args.prior_init, args.prior_depth_noise)
        else:
            result = run_step(name, commands[name], out, args.timeout, env)
        if summary := step_summary(name, result, out):
            result["summary"] = summary
        report["steps"].append(result)
        atomic_json(out / "report.json", report)
    speed = out / "speed.json"
    if speed.is_file():
        report["speed"] = json.loads(speed.read_text())
    nvs_speed = out / "nvs_speed" / "nvs_speed.json"
    if nvs_speed.is_file():
        report["nvs_speed"] = json.loads(nvs_speed.read_text())
    metrics = run_dir / "eval_test" / "metrics.json"
    if metrics.is_file():
        report["demo_metrics"] = json.loads(metrics.read_text())
    summary = run_dir / "train_summary.json"
    if summary.is_file():
        train = json.loads(summary.read_text())
        report["demo_training"] = {k: train[k] for k in ("steps", "seconds", "num_gaussians", "final_loss")}
    atomic_json(out / "report.json", report)
    (out / "report.md").write_text(markdown(report))
    print(markdown(report))
    failed = [s["step"] for s in report["steps"] if s["exit_code"] != 0]
    if failed:
        raise SystemExit(f"gpu-check: failed steps: {', '.join(failed)} (logs in {out})")


def step_summary(name: str, result: dict, out: Path) -> str | None:
    """The report's line for a test or speed step (pytest's counts; the cases ``speed.py`` measured, whose log ends
    on profiler warnings); None to show the log's last line."""
    if name in ("cuda-tests", "suite"):
        return pytest_counts(result["tail"])
    if name == "speed" and result["exit_code"] == 0 and (out / "speed.json").is_file():
        return f"{len(json.loads((out / 'speed.json').read_text())['results'])} cases (tables below)"
    if name == "nvs-speed" and result["exit_code"] == 0 and (out / "nvs_speed" / "nvs_speed.json").is_file():
        rows = json.loads((out / "nvs_speed" / "nvs_speed.json").read_text())["results"]
        best = max(rows, key=lambda r: r["images_per_second"])
        return (f"{len(rows)} cases, best {best['images_per_second']:.0f} images/s ({best['objects']} objects, "
                f"{best['precision']}, {best['kernels']} kernels; table below)")
    return None


def atomic_json(path: Path, value: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(value, indent=2) + "\n")
    os.replace(tmp, path)


def _number(value: float | None, spec: str) -> str:
    """``value`` formatted, ``-`` when it was not measured."""
    return "-" if value is None else format(value, spec)


def markdown(report: dict) -> str:
    m = report["machine"]
    machine = (f"{m.get('gpu')} ({m.get('gpu_memory_gib')} GiB, sm {m.get('compute_capability')}), driver "
               f"{m.get('driver')}, CUDA {m['cuda_runtime']}, torch {m['torch']}, gsplat {m['gsplat']}, "
               f"Python {m['python']}, {m['cpu_count']} CPU cores")
    lines = [f"# GPU check, {m['date']}", "", machine, "",
             "| step | exit | seconds | result |", "|---|---|---|---|"]
    for step in report["steps"]:
        result = step.get("summary") or (step["tail"][-1] if step["tail"] else "")
        lines.append(f"| {step['step']} | {step['exit_code']} | {step['seconds']} | {result[:120]} |")
    if "speed" in report:
        lines += ["", "| device | Gaussians | px | multi-view | render fwd ms | render bwd ms | step ms | steps/s |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in report["speed"]["results"]:
            lines.append(f"| {r['device']} | {r['gaussians']} | {r['resolution']} | {r['multiview']} "
                         f"| {r['render_forward_ms']:.2f} | {r['render_backward_ms']:.2f} "
                         f"| {r['train_step_ms']:.2f} | {r['steps_per_second']:.1f} |")
        profiled = [r for r in report["speed"]["results"] if "operators_per_step" in r]
        if profiled:
            lines += ["", "| Gaussians | px | multi-view | operators / step | CUDA kernels / step | host syncs / step |",
                      "|---|---|---|---|---|---|"]
            lines += [f"| {r['gaussians']} | {r['resolution']} | {r['multiview']} | {r['operators_per_step']:.0f} "
                      f"| {r['cuda_kernels_per_step']:.0f} | {r['host_syncs_per_step']:.1f} |" for r in profiled]
    if "nvs_speed" in report:
        lines += ["", "Novel-view prior's step (`benchmarks/nvs_speed.py`):", "",
                  "| objects | precision | kernels | batch ms | step ms | images/s | peak GiB | host syncs / step |",
                  "|---|---|---|---|---|---|---|---|"]
        lines += [f"| {r['objects']} | {r['precision']} | {r['kernels']} | {r['batch_ms']:.1f} | {r['step_ms']:.1f} "
                  f"| {r['images_per_second']:.0f} | {_number(r['peak_gib'], '.2f')} "
                  f"| {_number(r.get('host_syncs_per_step'), '.1f')} |"
                  for r in report["nvs_speed"]["results"]]
    if "demo_training" in report:
        t = report["demo_training"]
        rate = t["steps"] / max(t["seconds"], 1e-9)
        lines += ["", (f"Demo object, `diamond` preset: {t['steps']} steps in {t['seconds']:.0f} s "
                       f"({rate:.1f} steps/s), {t['num_gaussians']} Gaussians")]
    if "demo_metrics" in report:
        scores = report["demo_metrics"].get("summary", report["demo_metrics"])
        lines.append(f"Test split (novel views x novel lights): {json.dumps(scores)[:400]}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
