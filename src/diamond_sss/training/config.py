"""Training configuration: every hyperparameter of supplement Tab. 3 / Tab. 4, the two presets, overrides.

Presets:
    ``sss3dgs``  Tab. 4 "Original" (the SSS-3DGS release), no multi-view losses.
    ``diamond``  Tab. 3 / Tab. 4 "Best", with the multi-view silhouette (0.5) and depth (0.3) losses.

Any field can be overridden by ``--set key=value`` (repeatable) or by a JSON ``--config FILE`` holding a
flat object of fields (what ``diamond-sss tune`` writes). The resolved configuration is saved in the run.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from diamond_sss.errors import DataError
from diamond_sss.utils.io import read_json


def _key(default: Any, meaning: str) -> Any:
    """A :class:`TrainConfig` field with its meaning (``diamond-sss config`` and ``--set`` read it)."""
    return field(default=default, metadata={"help": meaning})


@dataclass
class TrainConfig:
    """Hyperparameters of one reconstruction. Learning rates per parameter group as in Tab. 3."""

    # schedule
    iterations: int = _key(10_000, "training steps")
    batch_size: int = _key(4, "images per training step")
    seed: int = _key(0, "seed of the regime selection, initialisation and every random draw")
    # learning rates (Tab. 3)
    position_lr_init: float = _key(0.00016, "initial learning rate of the means (times the scene radius)")
    position_lr_final: float = _key(0.0000016, "final learning rate of the means (exponential decay)")
    position_lr_delay_mult: float = _key(0.01, "learning rate factor of the means at the start of the delay")
    position_lr_delay_steps: int = _key(0, "steps of the means' learning rate warm-up delay")
    position_lr_max_steps: int = _key(30_000, "step at which the means' learning rate reaches its final value")
    normal_lr: float = _key(0.01, "learning rate of the normals")
    opacity_lr: float = _key(0.05, "learning rate of the opacities")
    scaling_lr: float = _key(0.005, "learning rate of the scales")
    rotation_lr: float = _key(0.001, "learning rate of the rotations")
    base_color_lr: float = _key(0.01, "learning rate of the base colours")
    roughness_lr: float = _key(0.01, "learning rate of the roughness")
    metallic_lr: float = _key(0.01, "learning rate of the metalness")
    subsurfacedness_lr: float = _key(0.01, "learning rate of the subsurfaceness")
    visibility_lr: float = _key(0.0025, "learning rate of the visibility SH coefficients")
    sss_lr: float = _key(0.001, "learning rate of the subsurface-scattering MLP")
    light_lr: float = _key(0.001, "learning rate of the log light scale")
    light_init: float = _key(-1.0, "initial log light scale (when not calibrated from the data)")
    light_init_from_data: bool = _key(True, "calibrate the initial light scale from the images")
    lr_decay_step: int = _key(50_000, "steps between step decays of every learning rate")
    lr_decay_factor: float = _key(0.1, "factor of each step decay")
    # Gaussians, initialisation and densification (gsplat DefaultStrategy)
    num_gaussians: int = _key(5_000, "initial number of Gaussians")
    init: str = _key("auto", "initialisation: auto | ply (points3d.ply) | hull (visual hull) | random")
    densify: bool = _key(True, "grow and prune Gaussians (false keeps the count fixed)")
    percent_dense: float = _key(0.01, "scale (fraction of the scene) above which a Gaussian is split, not cloned")
    densification_interval: int = _key(150, "steps between densifications")
    opacity_reset_interval: int = _key(1_000, "steps between opacity resets")
    densify_from_iter: int = _key(500, "first step of densification")
    densify_until_iter: int = _key(10_000, "last step of densification")
    densify_grad_threshold: float = _key(0.0010, "mean 2D gradient above which a Gaussian is densified")
    max_gaussians: int = _key(300_000, "cap on the number of Gaussians")
    # shading
    sss_width: int = _key(32, "hidden width of the subsurface-scattering MLP")
    random_background: bool = _key(False, "train on random background colours")
    # loss weights (Eq. A.1-A.7, Tab. 3)
    photometric_space: str = _key("srgb", "where L1 / D-SSIM compare images: srgb (as the SSS-3DGS release, which "
                                  "compares 8-bit sRGB values, and as the metrics) | linear radiance")
    lambda_dssim: float = _key(0.492, "weight of the D-SSIM term of the photometric loss")
    lambda_lpips: float = _key(0.171, "weight of the LPIPS loss")
    lambda_mask: float = _key(0.1, "weight of the mask (alpha vs object mask) loss")
    lambda_mask_entropy: float = _key(0.1, "weight of the mask entropy loss")
    lambda_normal: float = _key(0.037, "weight of the normal consistency loss")
    lambda_visibility: float = _key(0.01, "weight of the ray-traced visibility loss")
    lambda_incident_light: float = _key(0.015, "weight of the incident light regulariser")
    lambda_enh: float = _key(0.005, "weight of the base colour enhancement loss")
    lambda_base_color: float = _key(0.002, "weight of the base colour prior")
    lambda_base_color_smooth: float = _key(0.005, "weight of the base colour smoothness")
    lambda_metallic_smooth: float = _key(0.007, "weight of the metalness smoothness")
    lambda_roughness_smooth: float = _key(0.003, "weight of the roughness smoothness")
    lambda_subsurfacedness_smooth: float = _key(0.002, "weight of the subsurfaceness smoothness")
    lambda_sil: float = _key(0.5, "weight of the multi-view silhouette loss")
    lambda_depth: float = _key(0.3, "weight of the multi-view depth loss")
    synthetic_weight: float = _key(0.5, "loss weight of diffusion-generated images")
    # ray-traced visibility supervision (L_raytrace): every k steps, on a random subset of Gaussians
    raytrace_every: int = _key(10, "steps between ray-traced visibility supervisions")
    raytrace_gaussians: int = _key(1_024, "Gaussians ray-traced per supervision")
    raytrace_directions: int = _key(4, "directions traced per Gaussian")
    # multi-view consistency sampling (Sec. D); depth is smooth and sampled bilinearly, so the target views
    # give the same constraint at a fraction of the resolution
    mv_pairs_per_step: int = _key(2, "view pairs of the multi-view losses per step")
    mv_pixels_per_pair: int = _key(512, "pixels sampled per view pair")
    mv_target_mode: str = _key("nearest-k", "target view choice: nearest-k | random")
    mv_nearest_k: int = _key(4, "nearest views a target is drawn from (nearest-k)")
    mv_sil_threshold: float = _key(0.5, "alpha above which a pixel counts as inside the silhouette")
    mv_occlusion_tol: float = _key(0.02, "relative depth tolerance of the occlusion test")
    mv_charbonnier_eps: float = _key(0.0, "Charbonnier epsilon of the depth loss (0: L1)")
    mv_include_unobserved_views: bool = _key(True, "also draw targets among lattice views with no image")
    mv_target_downscale: int = _key(2, "resolution divisor of the target views")
    # runtime: these small kernels gain little from a second CPU thread and lose 10x when cores are
    # oversubscribed, hence one thread by default
    device: str = _key("auto", "auto | cpu | cuda[:i]")
    cpu_threads: int = _key(1, "torch intra-op threads on CPU (0: torch's default)")
    mixed_precision: bool = _key(True, "bfloat16 autocast of the subsurface-scattering MLP on CUDA")
    downscale: float = _key(1.0, "divide the image size by this factor")
    checkpoint_every: int = _key(500, "steps between checkpoints")
    log_every: int = _key(25, "steps between scalar logs")
    image_log_every: int = _key(500, "steps between TensorBoard image logs")
    lpips_weights: str = _key("", "LPIPS (VGG) weights in safetensors (empty: $DIAMOND_SSS_LPIPS_WEIGHTS)")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


PRESETS: dict[str, dict[str, Any]] = {
    "diamond": {},
    "sss3dgs": {
        "lambda_dssim": 0.2,
        "lambda_lpips": 0.2,
        "lambda_normal": 0.02,
        "lambda_visibility": 0.01,
        "lambda_incident_light": 0.02,
        "lambda_base_color": 0.005,
        "lambda_base_color_smooth": 0.006,
        "lambda_metallic_smooth": 0.002,
        "lambda_roughness_smooth": 0.002,
        "lambda_subsurfacedness_smooth": 0.002,
        "densification_interval": 100,
        "opacity_reset_interval": 3_000,
        "densify_from_iter": 500,
        "densify_until_iter": 15_000,
        "densify_grad_threshold": 0.0002,
        "lambda_sil": 0.0,
        "lambda_depth": 0.0,
    },
}


SCHEDULE_KEYS = ("position_lr_delay_steps", "position_lr_max_steps", "lr_decay_step", "densify_from_iter",
                 "densify_until_iter", "densification_interval", "opacity_reset_interval", "checkpoint_every",
                 "log_every", "image_log_every")
"""Step-valued keys: a run of another length scales them with :func:`scale_schedule`."""

SHORT_SCHEDULE: dict[str, int] = {
    "iterations": 1000, "position_lr_max_steps": 1000, "densify_from_iter": 250, "densify_until_iter": 850,
    "densification_interval": 125, "opacity_reset_interval": 10_001, "log_every": 50, "checkpoint_every": 500,
}
"""Tab. 3's schedule compressed for a run of a few hundred steps (demo, benchmarks), at 1000 steps:
densification from 25% to 85% of the run every 12.5%, no opacity reset (too short for the Gaussians to
recover), the position learning rate decaying over the run."""

CPU_BUDGET: dict[str, int] = {"batch_size": 1, "num_gaussians": 3_000, "max_gaussians": 8_000,
                              "mv_pairs_per_step": 1, "mv_pixels_per_pair": 256, "raytrace_gaussians": 512}
"""Batch 1, 3k initial Gaussians capped at 8k, lighter multi-view and ray-tracing sampling (64x64 on a CPU)."""

SHORT_RUN_MODEL: dict[str, Any] = {"sss_lr": 0.005, "sss_width": 64, "lambda_incident_light": 0.0}
"""What a run 80-100x shorter than the paper's (1000 steps, not 80-100k) needs, each measured on the demo
object (benchmarks/RESULTS.md, issue 17): the MLP learns 5x faster (+1.6 dB) and 2x wider (+0.5 dB), and the
incident light is not tied to the SH visibility, which ~10 ray-traced updates per Gaussian leave near its
initial value (the tie then forbids shadows: +0.5 dB)."""


SCHEDULE_FLOORS: dict[str, int] = {"densification_interval": 10, "opacity_reset_interval": 200}
"""Fewest steps a scaled run keeps for processes that take optimisation steps, whatever the run's length:
the gradient statistics of one densification (below ~10 steps a Gaussian is seen once or twice and the
noisy statistic densifies nearly all of them: 300k Gaussians after 50 steps) and the recovery of the
opacities after a reset (~100 Adam steps at ``opacity_lr`` to climb back from 0.01)."""


def scale_schedule(values: Mapping[str, Any], scale: float,
                   floors: Mapping[str, int] = SCHEDULE_FLOORS) -> dict[str, Any]:
    """``values`` with every :data:`SCHEDULE_KEYS` value times ``scale``, rounded down, at least 1 (0 stays 0)
    and never below ``min(value, floors[key])``.

    The one schedule scaler: ``train --iterations``, :func:`short_schedule` and the tuning trials (which pass
    no floors, so that every searched value stays distinct) use it.
    """
    if not scale > 0:
        raise ValueError(f"schedule scale must be positive, got {scale}")
    return {key: max(1, min(value, floors.get(key, 1)), math.floor(value * scale + 1e-9))
            if key in SCHEDULE_KEYS and value > 0 else value for key, value in values.items()}


def schedule_for(values: Mapping[str, Any], iterations: int) -> dict[str, Any]:
    """``iterations`` and the schedule keys of ``values`` (which holds its own ``iterations``) scaled to it."""
    if iterations <= 0:
        raise ValueError(f"iterations must be positive, got {iterations}")
    schedule = {key: values[key] for key in SCHEDULE_KEYS if key in values}
    return {"iterations": iterations, **scale_schedule(schedule, iterations / values["iterations"])}


def scaled_run_schedule(preset: str, iterations: int, config_file: Path | None = None,
                        sets: Sequence[str] = ()) -> tuple[dict[str, Any], dict[str, tuple[Any, Any]]]:
    """Overrides that scale the schedule of ``preset`` (+ ``config_file``) to ``iterations`` steps, and the
    changed keys as ``key -> (before, after)``. Keys given in ``sets`` are left to their ``--set`` value."""
    base = make_config(preset, config_file=config_file).to_dict()
    fixed = parse_sets(sets)
    scaled = {key: value for key, value in schedule_for(base, iterations).items() if key not in fixed}
    changes = {key: (base[key], value) for key, value in scaled.items() if key != "iterations" and value != base[key]}
    return scaled, changes


def short_schedule(iterations: int) -> dict[str, Any]:
    """Overrides for a reconstruction of ``iterations`` steps at 64x64 on a CPU: :data:`SHORT_SCHEDULE`
    scaled to ``iterations``, with :data:`CPU_BUDGET` and :data:`SHORT_RUN_MODEL`."""
    return {**schedule_for(SHORT_SCHEDULE, iterations), **CPU_BUDGET, **SHORT_RUN_MODEL}


def field_types() -> dict[str, type]:
    """Field name -> Python type of :class:`TrainConfig`."""
    hints = typing.get_type_hints(TrainConfig)
    return {f.name: hints[f.name] for f in fields(TrainConfig)}


def parse_value(key: str, text: str) -> Any:
    """Parse the string ``text`` as the type of field ``key``; clear errors for unknown keys and bad values."""
    types = field_types()
    if key not in types:
        close = [name for name in types if key.split("_")[-1] in name][:6]
        raise ValueError(f"unknown config key '{key}'" + (f"; similar keys: {close}" if close else ""))
    kind = types[key]
    text = text.strip()
    if kind is bool:
        lowered = text.lower()
        if lowered in ("1", "true", "yes", "on"):
            return True
        if lowered in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"config key '{key}' expects true/false, got '{text}'")
    if kind not in (int, float):
        return text
    try:
        number = float(text)
        if kind is int and not number.is_integer():
            raise ValueError
    except ValueError as exc:
        raise ValueError(f"config key '{key}' expects {kind.__name__}, got '{text}'") from exc
    return int(number) if kind is int else _finite(key, number)


def _finite(key: str, value: float) -> float:
    if not math.isfinite(value):
        raise ValueError(f"config key '{key}' must be a finite number, got {value}")
    return value


def _checked(key: str, value: Any) -> Any:
    types = field_types()
    if key not in types:
        raise ValueError(f"unknown config key '{key}'")
    kind = types[key]
    if isinstance(value, str) and kind is not str:
        return parse_value(key, value)
    if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return _finite(key, float(value))
    if kind is int and isinstance(value, float) and value.is_integer():
        return int(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ValueError(f"config key '{key}' expects {kind.__name__}, got {value!r}")
    return value


def parse_sets(sets: Sequence[str]) -> dict[str, Any]:
    """``["key=value", ...]`` (as given to ``--set``) -> typed overrides."""
    parsed: dict[str, Any] = {}
    for item in sets:
        if "=" not in item:
            raise ValueError(f"--set expects key=value, got '{item}'")
        key, text = item.split("=", 1)
        parsed[key.strip()] = parse_value(key.strip(), text)
    return parsed


def make_config(preset: str = "diamond", overrides: Mapping[str, Any] | None = None,
                config_file: Path | None = None, sets: Sequence[str] = ()) -> TrainConfig:
    """Resolve a configuration: preset, then ``config_file`` (JSON object), then ``overrides``, then ``sets``.

    ``sets`` are ``"key=value"`` strings as given to ``--set``.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset '{preset}'; presets: {sorted(PRESETS)}")
    values: dict[str, Any] = dict(PRESETS[preset])
    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():
            raise ValueError(f"config file not found: {path}")
        loaded = read_json(path)
        if not isinstance(loaded, dict):
            raise ValueError(f"{path}: expected a JSON object of config keys")
        for key, value in loaded.items():
            try:
                values[key] = _checked(key, value)
            except ValueError as exc:
                raise ValueError(f"{path}: {exc}") from exc
    for key, value in (overrides or {}).items():
        values[key] = _checked(key, value)
    values.update(parse_sets(sets))
    config = TrainConfig(**values)
    validate_config(config)
    return config


def validate_config(config: TrainConfig) -> None:
    """Reject values that cannot work, naming the key."""
    positive = ["iterations", "batch_size", "num_gaussians", "sss_width", "checkpoint_every", "log_every",
                "densification_interval", "raytrace_every", "max_gaussians", "mv_target_downscale"]
    for key in positive:
        if getattr(config, key) <= 0:
            raise ValueError(f"config key '{key}' must be positive, got {getattr(config, key)}")
    for f in fields(config):
        value = getattr(config, f.name)
        if (f.name.startswith("lambda_") or f.name == "synthetic_weight") and not value >= 0:
            raise ValueError(f"config key '{f.name}' must be >= 0, got {value}")
    if config.init not in ("auto", "ply", "hull", "random"):
        raise ValueError(f"config key 'init' must be auto|ply|hull|random, got '{config.init}'")
    if config.photometric_space not in ("linear", "srgb"):
        raise ValueError(f"config key 'photometric_space' must be linear|srgb, got '{config.photometric_space}'")
    if config.mv_target_mode not in ("nearest-k", "random"):
        raise ValueError(f"config key 'mv_target_mode' must be nearest-k|random, got '{config.mv_target_mode}'")
    if config.device not in ("auto", "cpu", "cuda") and not config.device.startswith("cuda:"):
        raise ValueError(f"config key 'device' must be auto|cpu|cuda[:i], got '{config.device}'")
    if config.downscale < 1:
        raise ValueError(f"config key 'downscale' must be >= 1, got {config.downscale}")


def describe_config(preset: str = "diamond") -> list[tuple[str, Any, str]]:
    """``(key, value, meaning)`` of every :class:`TrainConfig` field, with ``preset`` applied."""
    config = make_config(preset)
    return [(f.name, getattr(config, f.name), f.metadata["help"]) for f in fields(TrainConfig)]


def load_run_config(run: Path) -> TrainConfig:
    """The resolved configuration saved in a run folder (``config.json``)."""
    path = Path(run) / "config.json"
    if not path.is_file():
        raise ValueError(f"{run} is not a training run: {path} is missing")
    saved = read_json(path)
    if not isinstance(saved, dict):
        raise DataError(f"{path}: expected a JSON object of config keys")
    try:
        return make_config("diamond", overrides=saved)
    except ValueError as exc:
        raise DataError(f"{path}: {exc}") from exc
