"""The DIAMOND-SSS pipeline (supplement Sec. C.4): diffusion-augmented sparse reconstruction, end to end.

Stages, each cached and resumable and recorded in ``<out>/pipeline.json``:

1. ``prelim``   a reconstruction on the real images of the regime (geometry for conditioning, sanity checks),
                ``prelim_iterations`` steps (default: the final reconstruction's), or ``prelim_run``, a finished
                reconstruction of the same real images, reused without retraining;
2. ``nvs``      novel views: for each real light, the lattice views the regime left out (the ``nvs_views``
                farthest-point-spread ones when capped) generated from the nearest real view under that light;
3. ``relight``  every real and generated view relit to the lattice lights it lacks (the ``relight_lights``
                spread ones when capped), from the view's first light, geometry rendered from the preliminary
                reconstruction;
4. ``final``    the reconstruction on real images (photometric weight 1) and generated ones (weight
                ``synthetic_weight``, geometric losses at full weight), with the multi-view losses;
5. ``eval``     the test split (novel views under novel lights).

Generated images whose mask is empty or far from the preliminary reconstruction's silhouette
(IoU < ``min_silhouette_iou``) are dropped and counted. The result reports ``real_share``, the share of real
images among the final reconstruction's training images; with ``min_real_share`` the real images are repeated in
the training index until they make up at least that share of the images drawn (``real_draw_share``).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from diamond_sss.data.dataset import OLATDataset, directions_from
from diamond_sss.data.images import load_rgba
from diamond_sss.data.regimes import farthest_point_order, select_regime
from diamond_sss.diffusion.common.manifest import MANIFEST_NAME, read_image_manifest
from diamond_sss.evaluation.metrics import mask_iou
from diamond_sss.evaluation.run import evaluate_run
from diamond_sss.pipeline.capture import GeneratedImage, write_capture
from diamond_sss.pipeline.config import AUGMENTS, PipelineConfig
from diamond_sss.training.overrides import make_config
from diamond_sss.training.run import train_run
from diamond_sss.training.run_folder import load_scene
from diamond_sss.training.trainer import ImageSource
from diamond_sss.utils.io import atomic_write_json, move_aside, sha256_file, sha256_json


@dataclass
class StageRecord:
    name: str
    seconds: float
    counts: dict[str, Any] = field(default_factory=dict)


def read_manifest(path: Path) -> dict:
    """The JSON object in ``pipeline.json`` at ``path`` (``{}`` when there is none); a clear error when corrupt."""
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON ({error}); move it away or use another --out") from error
    if isinstance(data, dict):
        return data
    raise ValueError(f"{path} must hold a JSON object with 'inputs' and 'stages'; move it away or use another --out")


class PipelineManifest:
    """``pipeline.json``: inputs, seeds, model hashes and, per finished stage, its time and counts."""

    def __init__(self, path: Path, inputs: dict) -> None:
        self.path = path
        previous = read_manifest(path)
        if previous and previous.get("inputs") != inputs:
            raise ValueError(f"{path} belongs to a pipeline run with other inputs; use another --out")
        self.data = {"inputs": inputs, "stages": previous.get("stages", {})}

    def done(self, name: str) -> dict | None:
        return self.data["stages"].get(name)

    def record(self, stage: StageRecord) -> None:
        self.data["stages"][stage.name] = {"seconds": round(stage.seconds, 3), **stage.counts}
        atomic_write_json(self.path, self.data)


def move_aside_if_changed(out: Path, inputs: dict) -> Path | None:
    """Rename a run folder ``out`` whose ``pipeline.json`` records other ``inputs`` (a new model, other data) to
    ``<out>.<first 8 hex of its inputs' hash>`` (``-2``, ``-3``, ... if taken) and return the new path; ``None``
    when there is no previous run or it has the same inputs. Nothing is deleted."""
    recorded = read_manifest(out / "pipeline.json")
    if not recorded:
        return None
    previous = recorded.get("inputs")
    if previous == inputs:
        return None
    return move_aside(out, sha256_json(previous)[:8])


def shipped_augments() -> tuple[str, ...]:
    """The diffusion stages whose default model ships with the package."""
    from diamond_sss.diffusion.nvs.pipeline import default_model_dir
    from diamond_sss.diffusion.relight.inference import shipped_model_path

    available = []
    if (default_model_dir() / "config.json").is_file():
        available.append("nvs")
    if (shipped_model_path() / "config.json").is_file():
        available.append("relight")
    return tuple(available)


def parse_augment(text: str) -> tuple[str, ...]:
    """``auto`` (the stages whose model ships), ``none`` or a comma list of ``nvs`` / ``relight``."""
    text = text.strip()
    if text == "auto":
        return shipped_augments()
    stages = tuple(part.strip() for part in text.split(",") if part.strip() and part.strip() != "none")
    unknown = set(stages) - set(AUGMENTS)
    if unknown:
        raise ValueError(f"--augment: unknown stage(s) {sorted(unknown)}; use auto, none or a subset of {AUGMENTS}")
    return stages


def _model_hash(stage: str, folder: str | Path) -> str:
    from diamond_sss.diffusion.common.hashing import files_hash

    if not Path(folder).is_dir():
        raise FileNotFoundError(f"no {stage} model in {folder}: pass --{stage}-model PATH (train one with "
                                f"`diamond-sss finetune-{stage}`) or leave '{stage}' out of --augment")
    return files_hash(folder)


def check_prelim_run(run: Path, data: Path, split: str, observations: list[int]) -> Path:
    """``run`` when it is a finished reconstruction of exactly ``observations`` of ``data`` [``split``], else an
    error naming the file that differs."""
    run = Path(run)
    model = run / "model.safetensors"
    if not model.is_file():
        raise ValueError(f"prelim_run {run}: no finished reconstruction ({model} is missing)")
    recorded = read_manifest(run / "data.json")
    if recorded.get("data") != str(Path(data).resolve()) or recorded.get("split") != split:
        raise ValueError(f"prelim_run {run}: {run / 'data.json'} records data {recorded.get('data')!r} "
                         f"[{recorded.get('split')}], expected {str(Path(data).resolve())!r} [{split}]")
    used = read_manifest(run / "regime.json").get("observations")
    if used != observations:
        raise ValueError(f"prelim_run {run}: {run / 'regime.json'} lists other images ({used}) than the regime's "
                         f"real images ({observations})")
    return run


def real_copies(real: int, synthetic: int, share: float) -> int:
    """Extra copies of ``real`` images, next to ``synthetic`` ones, for the real ones to make up >= ``share``
    (in [0, 1)) of the training index: the least k >= 0 with ``(1 + k) real / ((1 + k) real + synthetic) >= share``."""
    if share <= 0.0 or synthetic == 0:
        return 0
    return max(0, math.ceil(share * synthetic / ((1.0 - share) * real) - 1.0 - 1e-9))


def spread_subset(indices: list[int], directions: torch.Tensor, count: int, seed: int) -> list[int]:
    """At most ``count`` of ``indices``, spread by farthest-point sampling of their directions."""
    if count <= 0 or count >= len(indices):
        return sorted(indices)
    order = farthest_point_order(directions[indices], count, torch.Generator().manual_seed(seed))
    return sorted(indices[i] for i in order)


def _silhouette_ok(path: Path, mask_path: Path | None, reference_alpha: torch.Tensor,
                   cfg: PipelineConfig) -> tuple[bool, str]:
    _, mask = load_rgba(path, mask_path)
    fraction = float((mask > 0.5).float().mean())
    if fraction < cfg.min_mask_fraction:
        return False, "empty_mask"
    if mask_iou(reference_alpha, mask) < cfg.min_silhouette_iou:
        return False, "silhouette"
    return True, "ok"


def run_pipeline(data: Path, out: Path, *, split: str = "train", regime: str = "views=5%,lights=5%",
                 preset: str = "diamond", overrides: dict[str, Any] | None = None, seed: int = 0,
                 config: PipelineConfig | None = None, show_progress: bool = True,
                 move_changed_run: bool = False) -> dict:
    """Run the stages above into ``out``; returns the final evaluation (plus counts) as a dict.

    A previous run in ``out`` with other inputs is an error, or with ``move_changed_run`` is moved aside
    (:func:`move_aside_if_changed`) and the run starts afresh."""
    cfg = config or PipelineConfig()
    unknown = set(cfg.augment) - set(AUGMENTS)
    if unknown:
        raise ValueError(f"--augment: unknown stage(s) {sorted(unknown)}; use none or a subset of {AUGMENTS}")
    if not 0.0 <= cfg.min_real_share < 1.0:
        raise ValueError(f"pipeline config 'min_real_share' must be in [0, 1), got {cfg.min_real_share}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    overrides = {**(overrides or {}), "seed": seed}
    train_cfg = make_config(preset, overrides=overrides)
    real = OLATDataset(data, split, downscale=train_cfg.runtime.downscale)
    selection = select_regime(real, regime, seed)
    model_hashes = {}
    if "nvs" in cfg.augment:
        from diamond_sss.diffusion.nvs.pipeline import default_model_dir

        model_hashes["nvs"] = _model_hash("nvs", cfg.nvs_model or default_model_dir())
    if "relight" in cfg.augment:
        from diamond_sss.diffusion.relight.inference import shipped_model_path

        model_hashes["relight"] = _model_hash("relight", cfg.relight_model or shipped_model_path())
    inputs = {
        "data": str(Path(data).resolve()), "split": split, "regime": regime, "preset": preset, "seed": seed,
        "overrides": overrides, "pipeline": asdict(cfg) | {"augment": list(cfg.augment)},
        "model_hashes": model_hashes, "data_hash": sha256_file(real.json_path),
    }
    prelim_dir = out / "prelim"
    if cfg.prelim_run and cfg.augment:
        prelim_dir = check_prelim_run(Path(cfg.prelim_run), data, split, selection.observations)
        inputs["prelim_model_hash"] = sha256_file(prelim_dir / "model.safetensors")
    if move_changed_run and (moved := move_aside_if_changed(out, inputs)) is not None:
        print(f"{out}: the inputs changed (models, data or settings); the previous run was moved to {moved}")
        out.mkdir(parents=True, exist_ok=True)
    manifest = PipelineManifest(out / "pipeline.json", inputs)
    real_views = set(selection.views)
    real_lights = set(selection.lights)
    center = real.bounds.center
    view_dirs = directions_from(real.camera_centers, center)
    light_dirs = directions_from(real.light_positions, center)

    def stage(name: str, body) -> dict:
        finished = manifest.done(name)
        if finished is not None:
            return finished
        started = time.perf_counter()
        counts = body()
        manifest.record(StageRecord(name, time.perf_counter() - started, counts))
        return manifest.done(name)

    def prelim_stage() -> dict:
        if cfg.prelim_run:
            return {"real_images": len(selection.observations), "reused": str(prelim_dir)}
        prelim_overrides = dict(overrides)
        if cfg.prelim_iterations is not None:
            prelim_overrides.update(iterations=cfg.prelim_iterations,
                                    position_lr_max_steps=cfg.prelim_iterations)
        result = train_run(data, prelim_dir, split=split, regime=regime, preset=preset, overrides=prelim_overrides,
                           show_progress=show_progress, resume=True)
        return {"real_images": len(selection.observations), "steps": result.steps}

    if cfg.augment:
        stage("prelim", prelim_stage)
    generated: list[GeneratedImage] = []
    dropped: dict[str, int] = {}
    prelim_alpha: dict[int, torch.Tensor] = {}
    prelim_scene = []

    def reference_alpha(view: int) -> torch.Tensor:
        if view not in prelim_alpha:
            if not prelim_scene:
                prelim_scene.append(load_scene(prelim_dir)[0])
            scene = prelim_scene[0]
            camera, light = real.cameras[view], real.lights[0]
            with torch.no_grad():
                render = scene.render(camera.w2c[None], camera.K[None], camera.width, camera.height,
                                      light.position[None], light.intensity[None])
            prelim_alpha[view] = render.gbuffer.alpha[0]
        return prelim_alpha[view]

    def keep(item: GeneratedImage) -> bool:
        ok, reason = _silhouette_ok(item.image, item.mask, reference_alpha(item.view), cfg)
        if not ok:
            dropped[reason] = dropped.get(reason, 0) + 1
        return ok

    nvs_dir = out / "nvs"
    if "nvs" in cfg.augment:
        missing = [v for v in range(real.num_views) if v not in real_views]
        targets = spread_subset(missing, view_dirs, cfg.nvs_views, seed)

        def nvs_stage() -> dict:
            from diamond_sss.diffusion.geometry.sources import RenderedGeometry
            from diamond_sss.diffusion.nvs.pipeline import generate_novel_views

            geometry = RenderedGeometry(prelim_dir, device=cfg.device)
            calls = 0
            for light in sorted(real_lights):
                sources = [v for v in sorted(real_views) if bool(real.presence[v, light])]
                if not sources or not targets:
                    continue
                nearest: dict[int, list[int]] = {}
                for target in targets:
                    similarity = view_dirs[sources] @ view_dirs[target]
                    nearest.setdefault(sources[int(torch.argmax(similarity))], []).append(target)
                for reference, group in nearest.items():
                    generate_novel_views(data, nvs_dir / f"l{light:03d}_v{reference:03d}", reference, light,
                                         group, split=split, model_dir=cfg.nvs_model,
                                         steps=cfg.nvs_steps, guidance_scale=cfg.nvs_guidance, seed=seed,
                                         cache_dir=cfg.cache_dir and Path(cfg.cache_dir) / "nvs",
                                         device=cfg.device, geometry=geometry)
                    calls += 1
            return {"targets": len(targets), "calls": calls}

        stage("nvs", nvs_stage)
        for manifest_path in sorted(nvs_dir.glob(f"*/{MANIFEST_NAME}")):
            generated += [item for item in read_image_manifest(manifest_path) if keep(item)]

    relight_dir = out / "relight"
    if "relight" in cfg.augment:
        sources = [GeneratedImage(o.view, o.light, o.image_path, o.mask_path)
                   for i, o in enumerate(real.observations) if i in set(selection.observations)] + generated
        combined_json = write_capture(relight_dir, "sources", real, sources)

        def relight_stage() -> dict:
            from diamond_sss.diffusion.common.cache import OutputCache
            from diamond_sss.diffusion.geometry.sources import RenderedGeometry
            from diamond_sss.diffusion.relight.inference import (
                default_cache_root,
                load_model,
                relight_view,
                write_relit,
            )

            model = load_model(cfg.relight_model, device=cfg.device)
            geometry = RenderedGeometry(prelim_dir, device=cfg.device)
            cache = OutputCache(Path(cfg.cache_dir) / "relight" if cfg.cache_dir else default_cache_root())
            dataset = OLATDataset(relight_dir, "sources")
            lights_of_view: dict[int, list[int]] = {}
            for obs in dataset.observations:
                lights_of_view.setdefault(obs.view, []).append(obs.light)
            results = []
            for view, lights in sorted(lights_of_view.items()):
                missing = [light for light in range(real.num_lights) if light not in lights]
                targets = spread_subset(missing, light_dirs, cfg.relight_lights, seed)
                results += relight_view(model, dataset, view, lights[0], targets, geometry, cache,
                                        num_steps=cfg.relight_steps, seed=seed, samples=cfg.relight_samples)
            write_relit(relight_dir / "out", results)
            return {"views": len(lights_of_view), "images": len(results), "sources_json": combined_json.name}

        stage("relight", relight_stage)
        generated += [item for item in read_image_manifest(relight_dir / "out" / MANIFEST_NAME) if keep(item)]

    extra = []
    num_real = len(selection.observations)
    copies = real_copies(num_real, len(generated), cfg.min_real_share)
    if generated:
        write_capture(out / "synthetic", "train", real, generated)
        extra = [ImageSource(real.subset(selection.observations), 1.0)] * copies + [
            ImageSource(OLATDataset(out / "synthetic", "train", downscale=train_cfg.runtime.downscale),
                        train_cfg.losses.synthetic_weight)]
    final_dir = out / "final"
    counts = {"real_images": num_real, "synthetic_images": len(generated), "dropped": dropped,
              "real_share": round(num_real / (num_real + len(generated)), 4),
              "real_draw_share": round((1 + copies) * num_real / ((1 + copies) * num_real + len(generated)), 4)}
    stage("final", lambda: {**counts, "dropped": dict(dropped),
                            "steps": train_run(data, final_dir, split=split, regime=regime, preset=preset,
                                               overrides=overrides, show_progress=show_progress, resume=True,
                                               extra_sources=extra).steps})
    if not (Path(data) / "transforms_test.json").is_file():
        return {**counts, "note": f"no transforms_test.json in {data}: evaluation skipped"}
    metrics = stage("eval", lambda: evaluate_run(final_dir, data, split="test", show_progress=show_progress))
    return {**metrics, **counts}
