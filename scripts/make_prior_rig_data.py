"""Prior training captures on varied light stages (issue 57 item 4: priors that generalise across rigs).

The priors were trained on one rig (cameras at radius 4 with a 32-degree field of view, lights at radius 5): the
relighting model never saw another light distance (which its light code ``diffusion.relight.light.light_code`` reads)
or framing, the novel-view model never another camera distance or field of view (which its Plucker rays read). This
renders captures each on its own seeded random rig:

* cameras at radius ``U[2.4, 6.5]``, the field of view set so that the object's bounding sphere fills ``U[45, 95]%``
  of the image width (the held-out rigs of ``scripts/make_heldout_data.sh``: 50-90%), on a band whose bottom is
  ``U[-0.6, 0]`` and top ``U[0.6, 0.95]`` (heights z/r);
* lights at radius ``U[2.5, 6.5]`` on a band from ``U[-1, -0.2]`` to ``U[0.8, 1]``;
* ``--kind relight`` (default): ``relight:6x10``, 6 views under 10 lights each (60 images of a 40 x 24 stage, 6.3%:
  within the 7% the relighting fine-tune may use) into ``outputs/relight_rigs/`` (~18 MB; the rigs drawn in
  ``outputs/relight_rigs_rigs.json``);
* ``--kind novel-view``: ``novelview:10x3``, 10 views under each of 3 lights (as ``scripts/make_prior_data.sh``) into
  ``outputs/priors/rig_*`` (rigs in ``outputs/priors_rigs.json``), then ``outputs/priors.tgz`` packed again (what
  ``scripts/gpu_lease.sh`` carries);

64 px, 64 spp, with depth/normal maps. Objects: the shape/material pairs that no benchmark, held-out judge
(``make_heldout_data.sh``), relighting judge or validation object (``benchmarks/relight_quality.py``) or fine-tuning
object uses, each on three rigs (novel views: without bunny/soap, a ``benchmarks/nvs_quality.py`` judge), and the 4
fine-tuning pairs on two new rigs each (new seeds: blobs are other shapes). Not committed; a capture whose
``meta.json`` exists is skipped, so a rerun resumes. About 7 minutes a kind on 2 CPU cores (Mitsuba). The relighting
model trains on them beside the embedded objects on a CPU (~40 min); the novel-view prior on a GPU::

    python scripts/make_prior_rig_data.py
    diamond-sss finetune-relight --out outputs/relight_rigs_model --steps 2000 --batch-size 6 --learning-rate 1e-3 \\
        --data src/diamond_sss/assets/data/finetune/* outputs/relight_rigs/*
    python scripts/make_prior_rig_data.py --kind novel-view   # then scripts/gpu_lease.sh (its header) trains it
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from diamond_sss.pipeline.rig import framed_intrinsics

ROOT = Path(__file__).resolve().parents[1]
NEW_PAIRS = ("blob:skin", "bunny:soap", "sphere:jade", "sphere:wax", "torus:glazed_wax", "torus:wax")
NOVEL_VIEW_JUDGES = ("bunny:soap",)
SUBSETS = {"relight": "relight:6x10", "novel-view": "novelview:10x3"}
FINETUNE_PAIRS = ("blob:soap", "bust:marble", "sphere:skin", "torus:jade")
FIRST_SEED = 101
FILL_RANGE = (0.45, 0.95)
CAMERA_RADIUS_RANGE = (2.4, 6.5)
LIGHT_RADIUS_RANGE = (2.5, 6.5)
FOV_RANGE_DEG = (25.0, 75.0)


def captures(kind: str) -> list[tuple[str, str, int]]:
    """``(shape, material, seed)`` of every capture of ``kind``, in render order (a capture keeps its seed, so its
    rig, whichever kind it belongs to)."""
    specs = [pair for pair in NEW_PAIRS for _ in range(3)] + [pair for pair in FINETUNE_PAIRS for _ in range(2)]
    excluded = NOVEL_VIEW_JUDGES if kind == "novel-view" else ()
    return [(*spec.split(":"), FIRST_SEED + i) for i, spec in enumerate(specs) if spec not in excluded]


def field_of_view_deg(camera_radius: float, fill: float) -> float:
    """Horizontal field of view (deg) at which a unit sphere at distance ``camera_radius`` spans ``fill`` of the
    width, as the pipeline frames cameras (``pipeline.rig.framed_intrinsics``; a 2-px image: ``fov = 2 atan(1 / f)``)."""
    focal = float(framed_intrinsics(torch.tensor([0.0, 0.0, camera_radius]), 1.0, 2, 2, fill)[0, 0])
    return 2.0 * math.degrees(math.atan(1.0 / focal))


def sample_rig(seed: int) -> dict[str, float | list[float]]:
    """A random light stage for ``seed`` (ranges in the module docstring); deterministic."""
    rng = np.random.default_rng(seed)
    while True:
        camera_radius = float(rng.uniform(*CAMERA_RADIUS_RANGE))
        fill = float(rng.uniform(*FILL_RANGE))
        fov = field_of_view_deg(camera_radius, fill)
        if FOV_RANGE_DEG[0] <= fov <= FOV_RANGE_DEG[1]:
            break
    return {
        "camera_radius": round(camera_radius, 3),
        "fov_x_deg": round(fov, 2),
        "fill": round(fill, 3),
        "camera_band": [round(float(rng.uniform(-0.6, 0.0)), 3), round(float(rng.uniform(0.6, 0.95)), 3)],
        "light_radius": round(float(rng.uniform(*LIGHT_RADIUS_RANGE)), 3),
        "light_band": [round(float(rng.uniform(-1.0, -0.2)), 3), round(float(rng.uniform(0.8, 1.0)), 3)],
    }


def synth_command(python: str, shape: str, material: str, seed: int, out: Path, rig: dict, subset: str) -> list[str]:
    return [
        python, "-m", "diamond_sss.cli.main", "synth", "--shape", shape, "--material", material, "--out", str(out),
        "--views", "40", "--lights", "24", "--test-views", "0", "--test-lights", "0", "--size", "64",
        "--spp", "64", "--seed", str(seed), "--subset", subset,
        "--camera-radius", str(rig["camera_radius"]), "--fov-x-deg", str(rig["fov_x_deg"]),
        "--camera-band", *map(str, rig["camera_band"]),
        "--light-radius", str(rig["light_radius"]), "--light-band", *map(str, rig["light_band"]),
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kind", choices=tuple(SUBSETS), default="relight", help="which prior the captures train")
    parser.add_argument("--python", default=sys.executable, help="interpreter that runs diamond-sss synth")
    args = parser.parse_args()
    if shutil.which(args.python) is None:
        parser.error(f"--python: {args.python} is not an executable (the interpreter of the project's .venv)")
    out, prefix = (ROOT / "outputs" / "relight_rigs", "") if args.kind == "relight" else (ROOT / "outputs" / "priors", "rig_")
    out.mkdir(parents=True, exist_ok=True)
    rigs, finished = {}, 0
    for shape, material, seed in tqdm(captures(args.kind), desc=f"{args.kind} captures", unit="capture"):
        name = f"{prefix}{shape}_{material}_s{seed}"
        rig = sample_rig(seed)
        rigs[name] = rig
        folder = out / name
        if (folder / "meta.json").is_file():  # written last: a finished capture
            finished += 1
            continue
        command = synth_command(args.python, shape, material, seed, folder, rig, SUBSETS[args.kind])
        try:
            subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        except subprocess.CalledProcessError as error:  # synth's own message is on stderr above
            print(f"make_prior_rig_data: synth stopped with exit {error.returncode} on {folder}; it has no meta.json, "
                  "so a rerun renders it again and keeps the finished captures", file=sys.stderr)
            return 1
    if finished:
        print(f"{finished} of {len(rigs)} captures were already finished (meta.json present) and were kept as they are")
    rig_file = out.with_name(f"{out.name}_rigs.json")  # beside the captures, so that <out>/* names only captures
    rig_file.write_text(json.dumps(rigs, indent=1))
    if args.kind == "novel-view":  # the form that travels to a lent GPU machine (scripts/gpu_lease.sh)
        single_rig = [p for p in out.iterdir() if not p.name.startswith(prefix) and (p / "meta.json").is_file()]
        subprocess.run(["tar", "czf", str(out.with_suffix(".tgz")), "-C", str(out.parent), out.name], check=True)
        print(f"packed {out} into {out.with_suffix('.tgz')} ({out.with_suffix('.tgz').stat().st_size / 2**20:.1f} MiB): "
              f"{len(rigs)} rig captures and {len(single_rig)} of scripts/make_prior_data.sh"
              + ("" if single_rig else " (none rendered yet: run it for the prior's single-rig captures, then this again)"))
    fills = [r["fill"] for r in rigs.values()]
    print(f"{len(rigs)} captures in {out}; object fills {min(fills):.0%}-{max(fills):.0%} of the width, "
          f"light radius {min(r['light_radius'] for r in rigs.values()):.1f}-"
          f"{max(r['light_radius'] for r in rigs.values()):.1f}; rigs: {rig_file}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
