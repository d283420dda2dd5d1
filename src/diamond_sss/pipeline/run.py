"""The DIAMOND-SSS pipeline (supplement Sec. C.4): diffusion-augmented sparse reconstruction, end to end.

Stages, each cached and resumable and recorded in ``<out>/pipeline.json``:

1. ``prelim``   a reconstruction on the real images of the regime (geometry for conditioning, sanity checks):
                preset ``prelim_preset`` with ``prelim_overrides`` (default: the final reconstruction's), for
                ``prelim_iterations`` steps (its schedule scaled to them; default: its own), or ``prelim_run``, a
                finished reconstruction of the same real images, reused without retraining;
2. ``nvs``      novel views: for each real light, the lattice views the regime left out (the ``nvs_views``
                farthest-point-spread ones when capped) generated from the nearest real view under that light;
                a capture with no lattice to generate on (only its sparse images) gets one first: cameras and
                lights placed around the real ones, or a rig file's (:mod:`~diamond_sss.pipeline.rig`);
3. ``relight``  every real and generated view relit to the lattice lights it lacks (the ``relight_lights``
                spread ones when capped), from the view's first light, geometry rendered from the preliminary
                reconstruction;
   ``repair``   (in place of 2 and 3, beyond the paper) the preliminary reconstruction's renders at the same
                targets, repaired (:mod:`~diamond_sss.diffusion.repair`);
4. ``final``    the reconstruction on real images (photometric weight 1) and generated ones (weight
                ``synthetic_weight``, times each image's agreement factor with the preliminary reconstruction
                when ``agreement_power`` > 0, :mod:`~diamond_sss.pipeline.agreement`; geometric losses at full
                weight; the initial hull carved with the generated views' masks too), with the configuration's
                multi-view losses (none under the short-run settings: ``PIPELINE_FINAL_RUN``);
5. ``eval``     the test split (novel views under novel lights).

With ``rounds`` > 1 the stages run again, each round's final reconstruction the next round's preliminary one. A
later ``repair`` round whose images' masks cover less than ``min_round_mask_area`` of the previous round's trains
nothing: its final reconstruction is the previous round's (copied), and so is every later round's.

Generated images whose mask is empty or far from the preliminary reconstruction's silhouette
(IoU < ``min_silhouette_iou``) are dropped and counted. The result reports ``real_share``, the share of real
images among the final reconstruction's training images; the real images are repeated in the training index until
they make up at least ``min_real_share`` of the images drawn (``real_draw_share``), by default a share that grows with
the regime: n / (n + ``generated_as_real``) for n real images.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tqdm.auto import tqdm

from diamond_sss.data.dataset import OLATDataset, directions_from
from diamond_sss.data.images import load_rgba, resize_area
from diamond_sss.data.regimes import RegimeSelection, farthest_point_order, select_regime
from diamond_sss.diffusion.common.manifest import MANIFEST_NAME, read_image_manifest
from diamond_sss.errors import DataError
from diamond_sss.evaluation.metrics import mask_iou
from diamond_sss.evaluation.run import evaluate_run
from diamond_sss.pipeline.agreement import agreement_factors, render_errors
from diamond_sss.pipeline.capture import GeneratedImage, check_on_lattice, write_capture
from diamond_sss.pipeline.config import AUGMENTS, REPAIR_ROUNDS, PipelineConfig
from diamond_sss.pipeline.rig import (
    RIG_FRAMINGS,
    LatticeSource,
    build_lattice,
    framed_camera_intrinsics,
    framed_capture_lattice,
    silhouette_radius,
)
from diamond_sss.runs.folder import load_scene, render_lattice_image
from diamond_sss.training.config import PIPELINE_KEYS, TrainConfig
from diamond_sss.training.overrides import make_config, rescheduled, with_values
from diamond_sss.training.run import train_run
from diamond_sss.training.trainer import ImageSource
from diamond_sss.utils.device import cpu_threads, resolve_device
from diamond_sss.utils.io import atomic_copy_tree, atomic_write_json, move_aside, sha256_file, sha256_json
from diamond_sss.utils.processes import idle_cpu_cores, threads_for_idle

if TYPE_CHECKING:
    from diamond_sss.diffusion.geometry import GeometrySource

logger = logging.getLogger(__name__)


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


_MISSING = object()

UNCOMPARED_SETTINGS = ("device", "cache_dir", "generation_threads")
"""Pipeline settings that ``pipeline.json`` records but a resumed run may change: where the diffusion models run,
on how many CPU threads, and where their outputs are cached do not change the images (up to CUDA's rounding; the
thread count not by a byte, tested), so a killed run can move from the CPU to a GPU or to another cache."""


def compared_inputs(inputs: Any) -> Any:
    """``inputs`` (a ``pipeline.json`` record) without the :data:`UNCOMPARED_SETTINGS`: what a resumed run must
    share with the recorded one. A record made while a pipeline setting was a reconstruction's key
    (:data:`~diamond_sss.training.config.PIPELINE_KEYS`) reads as the same run records it now: the final
    reconstruction's value (else the default) among the pipeline's settings, none in the overrides. A pipeline
    setting added since a run was recorded reads as its default (the behaviour from before it existed)."""
    if not (isinstance(inputs, dict) and isinstance(inputs.get("pipeline"), dict)):
        return inputs
    settings = {key: value for key, value in inputs["pipeline"].items() if key not in UNCOMPARED_SETTINGS}
    overrides = {key: dict(inputs[key]) for key in ("overrides", "prelim_overrides")
                 if isinstance(inputs.get(key), dict)}
    for dotted, setting in PIPELINE_KEYS.items():
        final = overrides.get("overrides", {})
        given = [final[key] for key in (dotted, setting) if key in final]
        settings.setdefault(setting, given[-1] if given else getattr(PipelineConfig(), setting))
        for record in overrides.values():
            record.pop(dotted, None)
            record.pop(setting, None)
    defaults = asdict(PipelineConfig())
    for key in defaults.keys() - set(UNCOMPARED_SETTINGS):
        settings.setdefault(key, list(defaults[key]) if isinstance(defaults[key], tuple) else defaults[key])
    return {**inputs, **overrides, "pipeline": settings}


def changed_inputs(recorded: Any, given: Any, prefix: str = "") -> list[str]:
    """``"key: recorded -> given"`` for each dotted key whose value differs between two nested ``inputs``
    records (a key one of them lacks reads ``missing``), sorted."""
    if isinstance(recorded, dict) and isinstance(given, dict):
        changed = []
        for key in sorted(set(recorded) | set(given), key=str):
            changed += changed_inputs(recorded.get(key, _MISSING), given.get(key, _MISSING), f"{prefix}{key}.")
        return changed
    if recorded == given:
        return []
    shown = ["missing" if value is _MISSING else repr(value) for value in (recorded, given)]
    return [f"{prefix.rstrip('.') or 'inputs'}: {shown[0]} -> {shown[1]}"]


def listed_changes(recorded: Any, given: Any, most: int = 6) -> str:
    """The first ``most`` of :func:`changed_inputs`, ``; ``-separated, and how many more there are."""
    changed = changed_inputs(recorded, given)
    more = f"; and {len(changed) - most} more" if len(changed) > most else ""
    return "; ".join(changed[:most]) + more


class PipelineManifest:
    """``pipeline.json``: inputs, seeds, model hashes and, per finished stage, its time and counts. The inputs
    are compared without the :data:`UNCOMPARED_SETTINGS` and recorded with those of the latest run."""

    def __init__(self, path: Path, inputs: dict) -> None:
        self.path = path
        previous = read_manifest(path)
        recorded, given = compared_inputs(previous.get("inputs")), compared_inputs(inputs)
        if previous and recorded != given:
            raise ValueError(f"{path} belongs to a pipeline run with other inputs "
                             f"({listed_changes(recorded, given)}); use another --out, or move that folder away")
        self.data = {"inputs": inputs, "stages": previous.get("stages", {})}

    def done(self, name: str) -> dict | None:
        return self.data["stages"].get(name)

    def record(self, stage: StageRecord) -> None:
        self.data["stages"][stage.name] = {"seconds": round(stage.seconds, 3), **stage.counts}
        atomic_write_json(self.path, self.data)

    def stage(self, name: str, body: Callable[[], dict]) -> dict:
        """The record of stage ``name``: the recorded one when it finished before, else ``body()``'s counts,
        timed and recorded."""
        finished = self.done(name)
        if finished is not None:
            return finished
        started = time.perf_counter()
        counts = body()
        self.record(StageRecord(name, time.perf_counter() - started, counts))
        return self.done(name)


def move_aside_if_changed(out: Path, inputs: dict) -> Path | None:
    """Rename a run folder ``out`` whose ``pipeline.json`` records other ``inputs`` (a new model, other data; compared
    without the :data:`UNCOMPARED_SETTINGS`) to ``<out>.<first 8 hex of its inputs' hash>`` (``-2``, ``-3``, ... if
    taken) and return the new path; ``None`` when there is no previous run or it has the same inputs. Nothing is
    deleted."""
    recorded = read_manifest(out / "pipeline.json")
    if not recorded:
        return None
    previous = recorded.get("inputs")
    if compared_inputs(previous) == compared_inputs(inputs):
        return None
    return move_aside(out, sha256_json(previous)[:8])


def shipped_augments() -> tuple[str, ...]:
    """What ``--augment auto`` runs: ``repair`` when its model ships with the package, else the paper's stages whose
    model ships (:data:`AUTO_AUGMENT_WHY`)."""
    from diamond_sss.diffusion.nvs.pipeline import default_model_dir
    from diamond_sss.diffusion.relight.inference import shipped_model_path
    from diamond_sss.diffusion.repair.pipeline import default_model_dir as repair_model_dir

    if (repair_model_dir() / "model.safetensors").is_file():
        return ("repair",)
    available = []
    if (default_model_dir() / "config.json").is_file():
        available.append("nvs")
    if (shipped_model_path() / "config.json").is_file():
        available.append("relight")
    return tuple(available)


AUTO_AUGMENT_WHY = ("render repair (beyond the paper): on four held-out objects of another rig given as only their 9 "
                    "images it scored +1.64 / +4.19 / +1.68 / +2.84 dB over SSS-3DGS, the paper's stages -0.24 / "
                    "+2.72 / -0.88 / +2.51 (benchmarks/RESULTS.md, session 45); without the repair model, the paper's "
                    "stages")
"""Why ``--augment auto`` picks what it picks (``diamond-sss run`` prints it)."""

def auto_framing(cfg: PipelineConfig) -> tuple[str, str]:
    """What ``--rig-framing auto`` resolves to for ``cfg`` and why (``diamond-sss run`` prints it)."""
    if cfg.rig is not None:
        return "real", "a --rig file's cameras keep the intrinsics it gives"
    if "repair" in cfg.augment:
        return "prior", ("the cameras repair generates at are zoomed on the object as the priors' training cameras "
                         "framed it; on a rig framing it at half that scale, +1.1 to +1.5 dB (benchmarks/RESULTS.md, "
                         "session 48)")
    return "real", ("the paper's stages keep the capture's framing: framed, with their reference view resampled to "
                    "match, they scored +0.30 / -0.52 dB over SSS-3DGS on a rig framing the object at half the priors' "
                    "scale, unframed +0.71 / -0.38 (benchmarks/RESULTS.md, session 49)")


def parse_augment(text: str) -> tuple[str, ...]:
    """``auto`` (:func:`shipped_augments`), ``none`` or a comma list of ``nvs`` / ``relight``, or ``repair``."""
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
        how = "repair-data` and `diamond-sss repair-train" if stage == "repair" else f"finetune-{stage}"
        raise FileNotFoundError(f"no {stage} model in {folder}: pass --{stage}-model PATH (train one with "
                                f"`diamond-sss {how}`) or leave '{stage}' out of --augment")
    return files_hash(folder)


def check_prelim_run(run: Path, real: OLATDataset, observations: list[int]) -> Path:
    """``run`` when it is a finished reconstruction of exactly ``observations`` of capture ``real`` (recorded at its
    path, or at another path with the same content digest: a moved capture), else an error naming the file that
    differs."""
    run = Path(run)
    model = run / "model.safetensors"
    if not model.is_file():
        raise ValueError(f"prelim_run {run}: no finished reconstruction ({model} is missing)")
    recorded = read_manifest(run / "data.json")
    moved = recorded.get("data") != str(real.root)
    other_split = recorded.get("split") != real.split
    if other_split or (moved and recorded.get("content_sha256") != real.content_hash(observations)):
        why = ("" if other_split else ": the images differ" if "content_sha256" in recorded else
               " (it records no content digest, by which a moved capture is recognised: trained before they were)")
        raise ValueError(f"prelim_run {run}: {run / 'data.json'} records data {recorded.get('data')!r} "
                         f"[{recorded.get('split')}], expected {str(real.root)!r} [{real.split}]{why}")
    used = read_manifest(run / "regime.json").get("observations")
    if used != observations:
        raise ValueError(f"prelim_run {run}: {run / 'regime.json'} lists other images ({used}) than the regime's "
                         f"real images ({observations})")
    if moved:
        logger.info("prelim_run %s: trained on %s, the same images as %s", run, recorded.get("data"), real.root)
    return run


def target_real_share(real: int, cfg: PipelineConfig) -> float:
    """The least share of real images among the images drawn: ``min_real_share`` when given, else
    ``real / (real + generated_as_real)`` (the generated images together drawn as often as that many real ones)."""
    if cfg.min_real_share is not None:
        return cfg.min_real_share
    return real / (real + cfg.generated_as_real)


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
    if mask_iou(resize_area(reference_alpha, *mask.shape[:2]), mask) < cfg.min_silhouette_iou:
        return False, "silhouette"
    return True, "ok"


@dataclass
class PipelineContext:
    """What the stages share: the run's inputs, the resolved configurations of the preliminary and the final
    reconstruction, the real capture, the regime's selection, the preliminary reconstruction's folder, the lattice the
    diffusion stages generate on (the capture's own, or one made for it: :mod:`~diamond_sss.pipeline.rig`) and its
    view and light directions."""

    data: Path
    out: Path
    split: str
    regime: str
    seed: int
    cfg: PipelineConfig
    prelim_cfg: TrainConfig
    train_cfg: TrainConfig
    real: OLATDataset
    selection: RegimeSelection
    prelim_dir: Path
    lattice: OLATDataset
    lattice_source: LatticeSource
    view_dirs: torch.Tensor
    light_dirs: torch.Tensor
    show_progress: bool


def checked_config(config: PipelineConfig | None) -> PipelineConfig:
    """``config`` (default: the defaults) once its values are checked, ``rounds`` given its default for the stages
    (:data:`~diamond_sss.pipeline.config.REPAIR_ROUNDS` with ``repair``, else 1), ``rig_framing`` of ``auto`` resolved
    (:func:`auto_framing`) and a ``device`` of ``auto`` resolved (CUDA when available, else CPU);
    a bad value is a ``ValueError`` naming the key."""
    cfg = config or PipelineConfig()
    unknown = set(cfg.augment) - set(AUGMENTS)
    if unknown:
        raise ValueError(f"--augment: unknown stage(s) {sorted(unknown)}; use none or a subset of {AUGMENTS}")
    if "repair" in cfg.augment and len(cfg.augment) > 1:
        raise ValueError(f"--augment {','.join(cfg.augment)}: repair takes the place of nvs and relight (it makes "
                         "the images of the same targets); give --augment repair alone")
    if cfg.min_real_share is not None and not 0.0 <= cfg.min_real_share < 1.0:
        raise ValueError(f"pipeline config 'min_real_share' must be in [0, 1), got {cfg.min_real_share}")
    if not (math.isfinite(cfg.generated_as_real) and cfg.generated_as_real > 0.0):
        raise ValueError(f"pipeline config 'generated_as_real' must be a finite number > 0, got {cfg.generated_as_real}")
    if cfg.rounds is None:
        cfg = replace(cfg, rounds=REPAIR_ROUNDS if "repair" in cfg.augment else 1)
    if isinstance(cfg.rounds, bool) or not isinstance(cfg.rounds, int) or cfg.rounds < 1:
        raise ValueError(f"pipeline config 'rounds' must be an integer >= 1, got {cfg.rounds!r}")
    if cfg.rounds > 1 and not cfg.augment:
        raise ValueError("pipeline config 'rounds' > 1 needs a diffusion stage (--augment): without generated images "
                         "every round is the same reconstruction")
    if cfg.prelim_iterations is not None and cfg.prelim_iterations <= 0:
        raise ValueError(f"pipeline config 'prelim_iterations' (--prelim-iterations) must be a positive number of "
                         f"training steps, got {cfg.prelim_iterations}")
    if not (math.isfinite(cfg.rig_view_angle) and 0.0 <= cfg.rig_view_angle <= 180.0):
        raise ValueError(f"pipeline config 'rig_view_angle' (--rig-view-angle) must be in [0, 180] degrees, got "
                         f"{cfg.rig_view_angle}")
    if cfg.rig_framing == "auto":
        cfg = replace(cfg, rig_framing=auto_framing(cfg)[0])
    if cfg.rig_framing not in RIG_FRAMINGS:
        raise ValueError(f"pipeline config 'rig_framing' (--rig-framing) must be auto or one of "
                         f"{', '.join(RIG_FRAMINGS)}, got {cfg.rig_framing!r}")
    if cfg.rig_framing == "prior" and cfg.rig is not None:
        raise ValueError(f"pipeline config 'rig_framing' (--rig-framing) prior: the cameras of --rig {cfg.rig} keep "
                         "the intrinsics the file gives; drop --rig-framing or the rig file")
    for key, least in (("rig_views", 0), ("rig_lights", 0), ("nvs_views", 0), ("relight_lights", 0), ("nvs_steps", 1), ("relight_steps", 1),
                       ("relight_samples", 1)):
        if getattr(cfg, key) < least:
            raise ValueError(f"pipeline config '{key}' (--{key.replace('_', '-')}) must be an integer >= {least}, "
                             f"got {getattr(cfg, key)}")
    if cfg.generation_threads is not None and cfg.generation_threads < 0:
        raise ValueError(f"pipeline config 'generation_threads' (--generation-threads) must be >= 0 (0: torch's "
                         f"default), or not given (the idle cores), got {cfg.generation_threads}")
    if not (math.isfinite(cfg.agreement_power) and cfg.agreement_power >= 0.0):
        raise ValueError(f"pipeline config 'agreement_power' must be a finite number >= 0, got {cfg.agreement_power}")
    if not (math.isfinite(cfg.synthetic_weight) and cfg.synthetic_weight >= 0.0):
        raise ValueError(f"pipeline config 'synthetic_weight' (--synthetic-weight) must be a finite number >= 0, got "
                         f"{cfg.synthetic_weight}")
    if not (math.isfinite(cfg.min_round_mask_area) and 0.0 <= cfg.min_round_mask_area <= 1.0):
        raise ValueError(f"pipeline config 'min_round_mask_area' (--min-round-mask-area) must be in [0, 1], got "
                         f"{cfg.min_round_mask_area}")
    if cfg.nvs_geometry is not None:
        from diamond_sss.diffusion.geometry import geometry_source
        from diamond_sss.diffusion.geometry.base import GeometryError

        try:
            geometry_source(cfg.nvs_geometry)
        except GeometryError as exc:
            raise ValueError(f"pipeline config 'nvs_geometry': {exc}") from exc
    if cfg.device != "auto":
        try:
            torch.device(cfg.device)  # a device that torch names; CUDA's presence is checked where a stage runs
        except RuntimeError as exc:
            raise ValueError(f"pipeline config 'device' (--device) must be auto | cpu | cuda[:i], got "
                             f"{cfg.device!r}") from exc
    return replace(cfg, device=str(resolve_device(cfg.device))) if cfg.device == "auto" else cfg


def prepare_run(data: Path, out: Path, *, split: str, regime: str, preset: str, overrides: dict[str, Any] | None,
                seed: int, cfg: PipelineConfig, prelim_overrides: dict[str, Any] | None = None,
                show_progress: bool) -> tuple[PipelineContext, dict]:
    """The shared state of a pipeline run into ``out`` (created once both configurations are resolved: a bad preset,
    key or value fails before anything is written) and its inputs as ``pipeline.json`` records them. The preliminary
    reconstruction's configuration is rescheduled to ``prelim_iterations`` here."""
    overrides = {**(overrides or {}), "seed": seed}
    prelim_preset = cfg.prelim_preset or preset
    prelim_overrides = overrides if prelim_overrides is None else {**prelim_overrides, "seed": seed}
    train_cfg = make_config(preset, overrides=overrides)
    prelim_cfg = make_config(prelim_preset, overrides=prelim_overrides)
    if cfg.prelim_iterations is not None:
        prelim_cfg = with_values(prelim_cfg, rescheduled(prelim_cfg, cfg.prelim_iterations))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    real = OLATDataset(data, split, downscale=train_cfg.runtime.downscale)
    if len(real.observations) < 2:
        raise DataError(f"{real.json_path}: {len(real.observations)} image; a reconstruction needs at least 2 "
                        "images of the object")
    selection = select_regime(real, regime, seed)
    model_hashes = {}
    if "nvs" in cfg.augment:
        from diamond_sss.diffusion.nvs.pipeline import default_model_dir

        model_hashes["nvs"] = _model_hash("nvs", cfg.nvs_model or default_model_dir())
    if "relight" in cfg.augment:
        from diamond_sss.diffusion.relight.inference import shipped_model_path

        model_hashes["relight"] = _model_hash("relight", cfg.relight_model or shipped_model_path())
    if "repair" in cfg.augment:
        from diamond_sss.diffusion.repair.pipeline import default_model_dir as repair_model_dir

        model_hashes["repair"] = _model_hash("repair", cfg.repair_model or repair_model_dir())
    inputs = {
        "data": str(Path(data).resolve()), "split": split, "regime": regime, "preset": preset, "seed": seed,
        "overrides": overrides, "prelim_overrides": prelim_overrides,
        "pipeline": asdict(cfg) | {"augment": list(cfg.augment)},
        "model_hashes": model_hashes, "data_hash": sha256_file(real.json_path),
    }
    prelim_dir = out / "prelim"
    if cfg.prelim_run and cfg.augment:
        prelim_dir = check_prelim_run(Path(cfg.prelim_run), real, selection.observations)
        inputs["prelim_model_hash"] = sha256_file(prelim_dir / "model.safetensors")
    lattice_source, lattice, inputs["lattice"] = generation_lattice(data, split, out, real, selection, cfg)
    if cfg.rig is not None:
        inputs["rig_sha256"] = sha256_file(cfg.rig)
    center = real.bounds.center
    ctx = PipelineContext(data, out, split, regime, seed, cfg, prelim_cfg, train_cfg, real, selection, prelim_dir,
                          lattice, lattice_source,
                          directions_from(lattice.camera_centers, center),
                          directions_from(lattice.light_positions, center), show_progress)
    return ctx, inputs


def lattice_has_targets(real: OLATDataset, selection: RegimeSelection, augment: tuple[str, ...]) -> bool:
    """Whether every stage of ``augment`` has something to generate on the capture's own lattice: ``nvs`` a camera
    the regime left out, ``relight`` a (view, light) pair the regime did not select, ``repair`` both."""
    needs = {"nvs": len(selection.views) < real.num_views,
             "relight": len(selection.observations) < real.num_views * real.num_lights}
    needs["repair"] = needs["nvs"] and needs["relight"]  # it makes what both make: new views and new lights
    return all(needs[stage] for stage in augment)


def generation_lattice(data: Path, split: str, out: Path, real: OLATDataset, selection: RegimeSelection,
                       cfg: PipelineConfig) -> tuple[LatticeSource, OLATDataset, str]:
    """The lattice the diffusion stages generate on: ``cfg.rig``'s when given; else the capture's own when each
    stage has something to generate on it (:func:`lattice_has_targets`; or nothing is generated), with its cameras
    that have no image framed as the priors' under ``rig_framing=prior``; else cameras and lights placed around the
    real ones (``rig_views`` / ``rig_lights``, framed by ``rig_framing``). Any but the capture's as it is is written
    to ``<out>/rig``. The third value names which: ``capture``, ``capture, framed``, ``rig`` or ``sampled``."""
    if cfg.rig is None and (not cfg.augment or lattice_has_targets(real, selection, cfg.augment)):
        if cfg.augment and cfg.rig_framing == "prior":
            return (*framed_capture_lattice(Path(out) / "rig", Path(data), split, selection.observations,
                                            downscale=real.downscale), "capture, framed")
        return LatticeSource(Path(data), split), real, "capture"
    if cfg.rig is None:
        logger.info("%s: no camera or light of the capture left to generate (%d images of %d views x %d lights): "
                    "placing %d cameras and %d lights around the real ones", real.json_path,
                    len(selection.observations), real.num_views, real.num_lights, cfg.rig_views, cfg.rig_lights)
    source, lattice = build_lattice(Path(out) / "rig", Path(data), split, selection.observations, rig_file=cfg.rig,
                                    views=cfg.rig_views, lights=cfg.rig_lights,
                                    max_view_angle_deg=cfg.rig_view_angle, downscale=real.downscale,
                                    framing=cfg.rig_framing)
    return source, lattice, "rig" if cfg.rig else "sampled"


class SilhouetteFilter:
    """Keeps the generated images whose mask is not empty and matches the preliminary reconstruction's silhouette
    (:func:`_silhouette_ok`) and counts the dropped ones by reason; each view's silhouette is rendered once."""

    def __init__(self, ctx: PipelineContext) -> None:
        self.ctx = ctx
        self.dropped: dict[str, int] = {}
        self._alpha: dict[int, torch.Tensor] = {}
        self._scene = None

    def reference_alpha(self, view: int) -> torch.Tensor:
        """The preliminary reconstruction's alpha at lattice view ``view`` under the first light."""
        if view not in self._alpha:
            if self._scene is None:
                self._scene = load_scene(self.ctx.prelim_dir)[0]
            render = render_lattice_image(self._scene, self.ctx.lattice, view, 0)
            self._alpha[view] = render.gbuffer.alpha[0]
        return self._alpha[view]

    def keep(self, items: list[GeneratedImage]) -> list[GeneratedImage]:
        """The ``items`` that pass, in order; the others are counted in :attr:`dropped`."""
        kept = []
        for item in check_on_lattice(items, self.ctx.lattice):
            ok, reason = _silhouette_ok(item.image, item.mask, self.reference_alpha(item.view), self.ctx.cfg)
            if ok:
                kept.append(item)
            else:
                self.dropped[reason] = self.dropped.get(reason, 0) + 1
        return kept


def threaded(cfg: PipelineConfig, stage: str, body: Callable[[], dict]) -> dict:
    """``body()`` (a generation stage) on ``cfg.generation_threads`` CPU threads, by default on the cores other
    processes leave idle at its start, said in one line; the threads are restored after it and left as they are on
    a GPU."""
    if torch.device(cfg.device).type != "cpu":
        return body()
    count = cfg.generation_threads
    if count is None:
        idle, usable = idle_cpu_cores()
        count = threads_for_idle(idle)
        print(f"{stage}: {count} CPU thread{'s' if count > 1 else ''} ({idle:.1f} of {usable} cores idle; "
              "--generation-threads sets it)")
    with cpu_threads(count):
        return body()


def prelim_stage(ctx: PipelineContext) -> dict:
    """The preliminary reconstruction on the regime's real images (or the reused ``prelim_run``)."""
    if ctx.cfg.prelim_run:
        return {"real_images": len(ctx.selection.observations), "reused": str(ctx.prelim_dir)}
    result = train_run(ctx.data, ctx.prelim_dir, ctx.prelim_cfg, split=ctx.split, regime=ctx.regime,
                       show_progress=ctx.show_progress, resume=True)
    return {"real_images": len(ctx.selection.observations), "steps": result.steps}


def nvs_geometry(cfg: PipelineConfig, prelim_dir: Path) -> GeometrySource:
    """The source of the real views' depth that the novel-view warp hint splats: ``cfg.nvs_geometry`` (a
    ``--geometry`` spec) when given, else the preliminary reconstruction in ``prelim_dir``."""
    from diamond_sss.diffusion.geometry import geometry_source
    from diamond_sss.diffusion.geometry.sources import RenderedGeometry

    if cfg.nvs_geometry is None:
        return RenderedGeometry(prelim_dir, device=cfg.device)
    return geometry_source(cfg.nvs_geometry, device=cfg.device)


def nvs_stage(ctx: PipelineContext) -> dict:
    """Novel views into ``<out>/nvs``: under each real light, the (spread) missing views generated from the nearest
    real view, at the model's resolution or the training size (the real images over ``runtime.downscale``) when that
    is smaller: the final reconstruction compares them with its render area-downsampled to their size."""
    from diamond_sss.diffusion.nvs.model import NVSModel
    from diamond_sss.diffusion.nvs.pipeline import default_model_dir, generate_novel_views

    cfg, lattice, source = ctx.cfg, ctx.lattice, ctx.lattice_source
    real_views = set(ctx.selection.views)
    missing = [v for v in range(lattice.num_views) if v not in real_views]
    targets = spread_subset(missing, ctx.view_dirs, cfg.nvs_views, ctx.seed)
    if not targets:
        why = (f"nvs_views is 0 of {len(missing)} missing views" if missing else
               f"every camera of the lattice ({lattice.json_path}) has a real image in the regime")
        logger.warning("nvs: no novel view to generate: %s", why)
        return {"targets": 0, "calls": 0, "why": why}
    geometry = nvs_geometry(cfg, ctx.prelim_dir)
    calls: list[tuple[int, int, list[int]]] = []  # (light, reference view, its targets)
    for light in sorted(set(ctx.selection.lights)):
        sources = [v for v in sorted(real_views) if bool(lattice.presence[v, light])]
        if not sources:
            continue
        nearest: dict[int, list[int]] = {}
        for target in targets:
            similarity = ctx.view_dirs[sources] @ ctx.view_dirs[target]
            nearest.setdefault(sources[int(torch.argmax(similarity))], []).append(target)
        calls += [(light, reference, group) for reference, group in nearest.items()]
    model = NVSModel.load(cfg.nvs_model or default_model_dir()).to(cfg.device)  # once for every call
    framed = framed_references(ctx, sorted({reference for _, reference, _ in calls}))
    for light, reference, group in tqdm(calls, desc="nvs", unit="call", disable=not ctx.show_progress,
                                        dynamic_ncols=True):
        generate_novel_views(source.data, ctx.out / "nvs" / f"l{light:03d}_v{reference:03d}", reference, light,
                             group, split=source.split, model_dir=cfg.nvs_model,
                             steps=cfg.nvs_steps, guidance_scale=cfg.nvs_guidance, seed=ctx.seed,
                             cache_dir=cfg.cache_dir and Path(cfg.cache_dir) / "nvs",
                             device=cfg.device, geometry=geometry, downscale=ctx.train_cfg.runtime.downscale,
                             canonical=cfg.nvs_canonical, model=model, reference_K=framed.get(reference))
    return {"targets": len(targets), "calls": len(calls), "references_framed": len(framed)}


def framed_references(ctx: PipelineContext, views: list[int]) -> dict[int, torch.Tensor]:
    """Under ``rig_framing=prior``, the intrinsics (at the lattice's size) in which the novel-view prior sees each
    reference view: framed as its training cameras, as the cameras it generates at are
    (:func:`~diamond_sss.pipeline.rig.framed_camera_intrinsics`); else none (the references as captured)."""
    if ctx.cfg.rig_framing != "prior" or not views:
        return {}
    capture = OLATDataset(ctx.data, ctx.split)
    center = capture.bounds.center.double()
    radius = silhouette_radius(capture, ctx.selection.observations, center)
    logger.info("nvs: the %d reference views resampled as the priors' training cameras frame the object "
                "(rig_framing=prior; its sphere of radius %.3g)", len(views), radius)
    return {view: framed_camera_intrinsics(ctx.lattice.cameras[view], center, radius) for view in views}


def nvs_images(ctx: PipelineContext) -> list[GeneratedImage]:
    """Every image the ``nvs`` stage generated, in folder order."""
    return [item for path in sorted((ctx.out / "nvs").glob(f"*/{MANIFEST_NAME}")) for item in read_image_manifest(path)]


def write_relight_sources(ctx: PipelineContext, generated: list[GeneratedImage]) -> Path:
    """The regime's real images and the ``generated`` ones as the capture ``<out>/relight`` [sources]."""
    chosen = set(ctx.selection.observations)
    sources = [GeneratedImage(o.view, o.light, o.image_path, o.mask_path)
               for i, o in enumerate(ctx.real.observations) if i in chosen] + generated
    return write_capture(ctx.out / "relight", "sources", ctx.lattice, sources)


def relight_stage(ctx: PipelineContext, sources_json: Path) -> dict:
    """Every view of the sources capture relit from its first light to the (spread) lattice lights it lacks, into
    ``<out>/relight/out``."""
    from diamond_sss.diffusion.common.cache import OutputCache
    from diamond_sss.diffusion.geometry.sources import RenderedGeometry
    from diamond_sss.diffusion.relight.inference import (
        default_cache_root,
        load_model,
        relight_view,
        write_relit,
    )

    cfg, relight_dir = ctx.cfg, ctx.out / "relight"
    model = load_model(cfg.relight_model, device=cfg.device)
    geometry = RenderedGeometry(ctx.prelim_dir, device=cfg.device)
    cache = OutputCache(Path(cfg.cache_dir) / "relight" if cfg.cache_dir else default_cache_root())
    dataset = OLATDataset(relight_dir, "sources")  # ctx.lattice: already downscaled (runtime.downscale)
    lights_of_view: dict[int, list[int]] = {}
    for obs in dataset.observations:
        lights_of_view.setdefault(obs.view, []).append(obs.light)
    results = []
    for view, lights in tqdm(sorted(lights_of_view.items()), desc="relight", unit="view",
                             disable=not ctx.show_progress, dynamic_ncols=True):
        missing = [light for light in range(ctx.lattice.num_lights) if light not in lights]
        targets = spread_subset(missing, ctx.light_dirs, cfg.relight_lights, ctx.seed)
        if targets:
            results += relight_view(model, dataset, view, lights[0], targets, geometry, cache,
                                    num_steps=cfg.relight_steps, seed=ctx.seed, samples=cfg.relight_samples)
    write_relit(relight_dir / "out", results)
    counts = {"views": len(lights_of_view), "images": len(results), "sources_json": sources_json.name}
    if not results:
        counts["why"] = ("relight_lights is 0" if cfg.relight_lights == 0 else
                         f"every view already has every light of the lattice ({ctx.lattice.json_path})")
        logger.warning("relight: no image to generate: %s", counts["why"])
    return counts


def repair_target_pairs(ctx: PipelineContext) -> list[tuple[int, int]]:
    """The (view, light) images ``repair`` makes: those the paper's two stages would generate. Under each real light
    the (spread) missing views, as ``nvs``; then for every view with an image the (spread) lattice lights it lacks,
    as ``relight``."""
    cfg, lattice = ctx.cfg, ctx.lattice
    real_views = set(ctx.selection.views)
    missing = [v for v in range(lattice.num_views) if v not in real_views]
    new_views = spread_subset(missing, ctx.view_dirs, cfg.nvs_views, ctx.seed)
    lights_of_view: dict[int, set[int]] = {}
    for index in ctx.selection.observations:
        obs = ctx.real.observations[index]
        lights_of_view.setdefault(obs.view, set()).add(obs.light)
    for view in new_views:
        lights_of_view[view] = set(ctx.selection.lights)
    pairs = [(view, light) for view in new_views for light in sorted(set(ctx.selection.lights))]
    for view, lights in sorted(lights_of_view.items()):
        lacking = [light for light in range(lattice.num_lights) if light not in lights]
        pairs += [(view, light) for light in spread_subset(lacking, ctx.light_dirs, cfg.relight_lights, ctx.seed)]
    return pairs


def repair_stage(ctx: PipelineContext) -> dict:
    """The preliminary reconstruction's renders at :func:`repair_target_pairs`, repaired, into ``<out>/repair``
    (at the model's resolution when the capture's images are larger: the final reconstruction compares them with its
    render area-downsampled to their size, as the novel views)."""
    from diamond_sss.diffusion.repair.inputs import RepairInputs
    from diamond_sss.diffusion.repair.pipeline import load_repair_model, repair_targets

    targets = repair_target_pairs(ctx)
    if not targets:
        why = (f"every camera and light of the lattice ({ctx.lattice.json_path}) has a real image in the regime, "
               "or nvs_views and relight_lights are 0")
        logger.warning("repair: no image to make: %s", why)
        return {"images": 0, "why": why}
    model = load_repair_model(ctx.cfg.repair_model, ctx.cfg.device)
    scene = load_scene(ctx.prelim_dir, ctx.cfg.device)[0].eval()
    builder = RepairInputs(scene, ctx.lattice, ctx.real, ctx.selection.observations,
                           size=model.config.resolution)  # the model's size, at most the capture's
    written = repair_targets(model, builder, targets, ctx.out / "repair", show_progress=ctx.show_progress)
    counts: dict[str, Any] = {"images": len(targets)}
    previous_round = previous_round_folder(ctx.out, ctx.prelim_dir)
    elsewhere = ctx.prelim_dir.parent.resolve() != ctx.out.resolve()  # not this round's own preliminary one
    if previous_round is None and elsewhere and (ctx.prelim_dir.parent / "repair" / MANIFEST_NAME).is_file():
        print(f"repair: the preliminary reconstruction ({ctx.prelim_dir}) is a round of another pipeline, not a "
              "previous round of this one: no mask area compared, this round trains")
    if previous_round is None or not (previous_round / "repair" / MANIFEST_NAME).is_file():
        return counts
    return {**counts, **round_decision(ctx.cfg, written, previous_round)}


def previous_round_folder(out: Path, prelim_dir: Path) -> Path | None:
    """The folder of the round before the one running into ``out`` when ``prelim_dir`` is that round's final
    reconstruction as :func:`run_pipeline` lays the rounds out (``out/round<R-1>/final`` for the last round,
    ``<out's parent>/round<k-1>/final`` for round ``k`` in ``round<k>``); None for a first round, and for a
    ``--prelim-run`` from anywhere else (another pipeline's final is not a previous round of this one)."""
    out, prelim_dir = Path(out).resolve(), Path(prelim_dir).resolve()
    folder = prelim_dir.parent
    number = folder.name.removeprefix("round")
    if prelim_dir.name != "final" or not folder.name.startswith("round") or not number.isdigit():
        return None
    if folder.parent == out or (folder.parent == out.parent and out.name == f"round{int(number) + 1}"):
        return folder
    return None


def round_decision(cfg: PipelineConfig, written: list[GeneratedImage], previous_round: Path) -> dict[str, Any]:
    """Whether a later round trains (the repair stage's record, printed): ``mask_area_vs_previous_round``, the
    :func:`mask_area_ratio` of its ``written`` images against ``previous_round``'s, and ``keep_previous_round``, why
    it keeps the previous round's final reconstruction instead (a ratio under ``min_round_mask_area``, or a previous
    round that kept its own), when it does."""
    kept_before = (read_manifest(previous_round / "pipeline.json").get("stages", {}).get("final") or {}).get("kept")
    if kept_before is not None:
        why = f"the previous round ({previous_round}) kept the final reconstruction of the round before it"
        print(f"repair: {why}; so does this round")
        return {"keep_previous_round": why}
    compared = mask_area_ratio(written, read_image_manifest(previous_round / "repair" / MANIFEST_NAME))
    if compared is None:
        print(f"repair: no mask area compared with the previous round ({previous_round}): it shares no view and light "
              "with this round, or its masks are empty; this round trains")
        return {}
    ratio, shared = compared
    record: dict[str, Any] = {"mask_area_vs_previous_round": round(ratio, 4)}
    area = f"the generated masks cover {100.0 * ratio:.1f}% of the previous round's area ({shared} images)"
    if ratio >= cfg.min_round_mask_area:
        caveat = ("; the threshold was measured with the shipped repair model, not --repair-model's: "
                  "benchmarks/rounds.py on your runs measures it for yours" if cfg.repair_model is not None else "")
        print(f"repair: {area}, at least min_round_mask_area ({100.0 * cfg.min_round_mask_area:.0f}%): this round "
              f"trains{caveat}")
        return record
    why = (f"{area}, under min_round_mask_area ({100.0 * cfg.min_round_mask_area:.0f}%): the previous round's final "
           "reconstruction shrank the outline it was given (issue 58); at 90-93% a further round changed the test "
           "PSNR by -0.14 dB and the mask IoU by -0.019 on average (33 runs, 2 rigs), at 95-99% by +0.26 dB (32 "
           "runs, 2 rigs)")
    print(f"repair: {why}; this round keeps the previous round's final reconstruction (--min-round-mask-area 0 trains "
          "it anyway)")
    return {**record, "keep_previous_round": why}


def keep_previous_round(ctx: PipelineContext, why: str) -> dict:
    """The final stage of a round that trains nothing (:func:`round_decision`): the previous round's final
    reconstruction (this round's preliminary one) copied into ``<out>/final``; its record is the previous round's
    (image counts) with ``kept``, the folder copied, and ``why``."""
    final = ctx.out / "final"
    if not final.exists():  # a whole copy, or none (a run killed while copying makes it again)
        atomic_copy_tree(ctx.prelim_dir, final)
    previous = read_manifest(ctx.prelim_dir.parent / "pipeline.json").get("stages", {}).get("final", {})
    return {**{key: value for key, value in previous.items() if key != "seconds"}, "kept": str(ctx.prelim_dir),
            "why": why}


def mask_area_ratio(current: list[GeneratedImage], previous: list[GeneratedImage]) -> tuple[float, int] | None:
    """``sum_i A(current_i) / sum_i A(previous_i)`` over the images both lists hold (same view and light), with
    ``A`` the sum of a mask's values (its area in pixels), and how many they share; None when they share none or the
    previous masks are empty."""
    before = {(item.view, item.light): item for item in previous}
    shared = [(item, before[item.view, item.light]) for item in current if (item.view, item.light) in before]
    if not shared:
        return None
    area_now = sum(float(load_rgba(item.image, item.mask)[1].sum()) for item, _ in shared)
    area_before = sum(float(load_rgba(item.image, item.mask)[1].sum()) for _, item in shared)
    return (area_now / area_before, len(shared)) if area_before > 0 else None


def repaired_images(ctx: PipelineContext) -> list[GeneratedImage]:
    """Every image the ``repair`` stage made."""
    return read_image_manifest(ctx.out / "repair" / MANIFEST_NAME)


def relit_images(ctx: PipelineContext) -> list[GeneratedImage]:
    """Every image the ``relight`` stage generated."""
    return read_image_manifest(ctx.out / "relight" / "out" / MANIFEST_NAME)


def final_sources(ctx: PipelineContext, generated: list[GeneratedImage],
                  dropped: dict[str, int]) -> tuple[list[ImageSource], dict]:
    """The final reconstruction's image sources besides the regime's real images (the ``generated`` ones written to
    ``<out>/synthetic`` and the real ones repeated for ``min_real_share``) and the counts it records."""
    num_real = len(ctx.selection.observations)
    copies = real_copies(num_real, len(generated), target_real_share(num_real, ctx.cfg))
    extra, factors = [], []
    if generated:
        write_capture(ctx.out / "synthetic", "train", ctx.lattice, generated)
        # ctx.real's lattice and images made at its size: already downscaled (runtime.downscale), read as they are
        synthetic = OLATDataset(ctx.out / "synthetic", "train")
        if ctx.cfg.agreement_power > 0.0:
            prelim = load_scene(ctx.prelim_dir, resolve_device(ctx.train_cfg.runtime.device))[0]
            errors = render_errors(prelim, ctx.lattice, generated)
            factor_of = dict(zip(((item.view, item.light) for item in generated),
                                 agreement_factors(errors, ctx.cfg.agreement_power), strict=True))
            factors = [factor_of[obs.view, obs.light] for obs in synthetic.observations]
        extra = [ImageSource(ctx.real.subset(ctx.selection.observations), 1.0)] * copies + [
            ImageSource(synthetic, ctx.cfg.synthetic_weight, tuple(factors) if factors else None)]
    counts = {"real_images": num_real, "synthetic_images": len(generated), "dropped": dropped,
              "real_share": round(num_real / (num_real + len(generated)), 4),
              "real_draw_share": round((1 + copies) * num_real / ((1 + copies) * num_real + len(generated)), 4)}
    if factors:
        counts["agreement"] = {"mean_factor": round(sum(factors) / len(factors), 4),
                               "min_factor": round(min(factors), 4),
                               "down_weighted": sum(factor < 1.0 for factor in factors)}
    return extra, counts


def final_stage(ctx: PipelineContext, extra: list[ImageSource], counts: dict) -> dict:
    """The final reconstruction into ``<out>/final`` on the real images and the ``extra`` sources."""
    result = train_run(ctx.data, ctx.out / "final", ctx.train_cfg, split=ctx.split, regime=ctx.regime,
                       show_progress=ctx.show_progress, resume=True, extra_sources=extra)
    return {**counts, "steps": result.steps}


def nothing_generated(manifest: PipelineManifest, cfg: PipelineConfig, dropped: dict[str, int]) -> str:
    """Why augmentation asked for (``cfg.augment``) left no generated image, and the fix: the message of the error
    that stops the run before a final reconstruction that would quietly skip the method."""
    reasons = [f"{stage}: {record['why']}" for stage in cfg.augment
               if (record := manifest.done(stage)) is not None and "why" in record]
    if dropped:
        reasons.append("every generated image was dropped (" + ", ".join(f"{k}: {v}" for k, v in
                       sorted(dropped.items())) + "): they disagree with the preliminary reconstruction's silhouette; "
                       "check it (<out>/prelim) or lower min_silhouette_iou / min_mask_fraction")
    return (f"--augment {','.join(cfg.augment)} generated no image ({'; '.join(reasons) or 'no stage made one'}); "
            "give a regime that leaves cameras or lights of the capture out, a rig (--rig FILE), more placed cameras "
            "and lights (rig_views / rig_lights), or --augment none for a reconstruction on the real images alone")


def eval_stage(ctx: PipelineContext) -> dict:
    """The final reconstruction's metrics on the test split."""
    return evaluate_run(ctx.out / "final", ctx.data, split="test", show_progress=ctx.show_progress)


def run_pipeline(data: Path, out: Path, *, split: str = "train", regime: str = "views=5%,lights=5%",
                 preset: str = "diamond", overrides: dict[str, Any] | None = None,
                 prelim_overrides: dict[str, Any] | None = None, seed: int = 0,
                 config: PipelineConfig | None = None, show_progress: bool = True,
                 move_changed_run: bool = False) -> dict:
    """Run the stages above into ``out``; returns the final evaluation (plus counts) as a dict.

    ``overrides``: config overrides of the final reconstruction; ``prelim_overrides``: of the preliminary one
    (default: the same as the final's).

    A previous run in ``out`` with other inputs is an error, or with ``move_changed_run`` is moved aside
    (:func:`move_aside_if_changed`) and the run starts afresh. With ``rounds`` = R > 1, rounds 1..R-1 run into
    ``out/round<k>`` first, each the next one's preliminary reconstruction; the last round runs into ``out`` and the
    result lists every round's test PSNR under ``round_psnr``."""
    cfg = checked_config(config)
    round_psnr = []
    for k in range(1, cfg.rounds):
        result = run_pipeline(data, Path(out) / f"round{k}", split=split, regime=regime, preset=preset,
                              overrides=overrides, prelim_overrides=prelim_overrides, seed=seed,
                              config=replace(cfg, rounds=1),
                              show_progress=show_progress, move_changed_run=move_changed_run)
        round_psnr.append(result.get("psnr"))
        cfg = replace(cfg, prelim_run=str(Path(out) / f"round{k}" / "final"))
    ctx, inputs = prepare_run(data, out, split=split, regime=regime, preset=preset, overrides=overrides,
                              prelim_overrides=prelim_overrides, seed=seed, cfg=cfg, show_progress=show_progress)
    if move_changed_run:
        recorded = read_manifest(ctx.out / "pipeline.json").get("inputs")
        if (moved := move_aside_if_changed(ctx.out, inputs)) is not None:
            print(f"{ctx.out}: the inputs changed ({listed_changes(compared_inputs(recorded), compared_inputs(inputs))})"
                  f"; the previous run was moved to {moved}")
            ctx.out.mkdir(parents=True, exist_ok=True)
    manifest = PipelineManifest(ctx.out / "pipeline.json", inputs)
    if cfg.augment:
        manifest.stage("prelim", lambda: prelim_stage(ctx))
    silhouettes = SilhouetteFilter(ctx)
    generated: list[GeneratedImage] = []
    if "nvs" in cfg.augment:
        manifest.stage("nvs", lambda: threaded(cfg, "novel views", lambda: nvs_stage(ctx)))
        generated += silhouettes.keep(nvs_images(ctx))
    if "relight" in cfg.augment:
        sources_json = write_relight_sources(ctx, generated)
        manifest.stage("relight", lambda: threaded(cfg, "relighting", lambda: relight_stage(ctx, sources_json)))
        generated += silhouettes.keep(relit_images(ctx))
    kept = None
    if "repair" in cfg.augment:
        kept = manifest.stage("repair", lambda: threaded(cfg, "repair", lambda: repair_stage(ctx))).get(
            "keep_previous_round")
        if kept is None and (ctx.out / "repair" / MANIFEST_NAME).is_file():
            generated += silhouettes.keep(repaired_images(ctx))
    if kept is not None:
        record = manifest.stage("final", lambda: keep_previous_round(ctx, kept))
        counts = {key: value for key, value in record.items() if key != "seconds"}
    else:
        if cfg.augment and not generated:
            raise ValueError(nothing_generated(manifest, cfg, silhouettes.dropped))
        extra, counts = final_sources(ctx, generated, silhouettes.dropped)
        manifest.stage("final", lambda: final_stage(ctx, extra, counts))
    if not (Path(data) / "transforms_test.json").is_file():
        return {**counts, "note": f"no transforms_test.json in {data}: evaluation skipped"}
    metrics = manifest.stage("eval", lambda: eval_stage(ctx))
    return {**metrics, **counts, **({"round_psnr": [*round_psnr, metrics.get("psnr")]} if round_psnr else {})}
