"""Training configuration: every hyperparameter of supplement Tab. 3 / Tab. 4, the two presets, overrides.

Presets:
    ``sss3dgs``  Tab. 4 "Original" (the SSS-3DGS release), no multi-view losses.
    ``diamond``  Tab. 3 / Tab. 4 "Best", with the multi-view silhouette (0.5) and depth (0.3) losses.

Any field can be overridden by ``--set key=value`` (repeatable) or by a JSON ``--config FILE`` holding a
flat object of fields (what ``diamond-sss tune`` writes). The resolved configuration is saved in the run.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any


@dataclass
class TrainConfig:
    """Hyperparameters of one reconstruction. Learning rates per parameter group as in Tab. 3."""

    # schedule
    iterations: int = 10_000
    batch_size: int = 4
    seed: int = 0
    # learning rates (Tab. 3); means use position_lr_* with exponential decay, scaled by the scene radius
    position_lr_init: float = 0.00016
    position_lr_final: float = 0.0000016
    position_lr_delay_mult: float = 0.01
    position_lr_delay_steps: int = 0
    position_lr_max_steps: int = 30_000
    normal_lr: float = 0.01
    opacity_lr: float = 0.05
    scaling_lr: float = 0.005
    rotation_lr: float = 0.001
    base_color_lr: float = 0.01
    roughness_lr: float = 0.01
    metallic_lr: float = 0.01
    subsurfacedness_lr: float = 0.01
    visibility_lr: float = 0.0025
    sss_lr: float = 0.001
    light_lr: float = 0.001
    light_init: float = -1.0
    light_init_from_data: bool = True
    lr_decay_step: int = 50_000
    lr_decay_factor: float = 0.1
    # Gaussians, initialisation and densification (gsplat DefaultStrategy; densify=False keeps N fixed)
    num_gaussians: int = 5_000
    init: str = "auto"
    densify: bool = True
    percent_dense: float = 0.01
    densification_interval: int = 150
    opacity_reset_interval: int = 1_000
    densify_from_iter: int = 500
    densify_until_iter: int = 10_000
    densify_grad_threshold: float = 0.0010
    max_gaussians: int = 300_000
    # shading
    sss_width: int = 32
    random_background: bool = False
    # loss weights (Eq. A.1-A.7, Tab. 3); photometric_space: where L1 / D-SSIM compare images, "linear"
    # radiance or "srgb" (the space of the metrics, which weighs dark regions as the eye and PSNR do)
    photometric_space: str = "linear"
    lambda_dssim: float = 0.492
    lambda_lpips: float = 0.171
    lambda_mask: float = 0.1
    lambda_mask_entropy: float = 0.1
    lambda_normal: float = 0.037
    lambda_visibility: float = 0.01
    lambda_incident_light: float = 0.015
    lambda_enh: float = 0.005
    lambda_base_color: float = 0.002
    lambda_base_color_smooth: float = 0.005
    lambda_metallic_smooth: float = 0.007
    lambda_roughness_smooth: float = 0.003
    lambda_subsurfacedness_smooth: float = 0.002
    lambda_sil: float = 0.5
    lambda_depth: float = 0.3
    synthetic_weight: float = 0.5
    # ray-traced visibility supervision (L_raytrace): every k steps, on a random subset of Gaussians
    raytrace_every: int = 10
    raytrace_gaussians: int = 1_024
    raytrace_directions: int = 4
    # multi-view consistency sampling (Sec. D); target views are rendered at 1/mv_target_downscale resolution
    # (depth is smooth and sampled bilinearly, so the constraint is the same at a fraction of the cost)
    mv_pairs_per_step: int = 2
    mv_pixels_per_pair: int = 512
    mv_target_mode: str = "nearest-k"
    mv_nearest_k: int = 4
    mv_sil_threshold: float = 0.5
    mv_occlusion_tol: float = 0.02
    mv_charbonnier_eps: float = 0.0
    mv_include_unobserved_views: bool = True
    mv_target_downscale: int = 2
    # runtime; cpu_threads: torch intra-op threads on CPU (0 = torch's default). One thread is the default:
    # these small kernels gain little from a second thread and lose 10x when cores are oversubscribed.
    device: str = "auto"
    cpu_threads: int = 1
    mixed_precision: bool = True
    downscale: float = 1.0
    checkpoint_every: int = 500
    log_every: int = 25
    image_log_every: int = 500
    lpips_weights: str = ""

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


def short_schedule(iterations: int) -> dict[str, Any]:
    """Overrides for a reconstruction of a few hundred steps at 64x64 on a CPU (demo, tests, benchmarks).

    Tab. 3's schedule compressed to ``iterations``: densification from 25% to 85% of the run every ~12%,
    no opacity reset (too short for the Gaussians to recover), the position learning rate decaying over the
    run, batch 1, 3k initial Gaussians capped at 8k, lighter multi-view and ray-tracing sampling.
    """
    return {
        "iterations": iterations,
        "position_lr_max_steps": iterations,
        "batch_size": 1,
        "num_gaussians": 3_000,
        "max_gaussians": 8_000,
        "densify_from_iter": max(1, iterations // 4),
        "densify_until_iter": max(2, int(iterations * 0.85)),
        "densification_interval": max(1, iterations // 8),
        "opacity_reset_interval": 10 * iterations + 1,
        "mv_pairs_per_step": 1,
        "mv_pixels_per_pair": 256,
        "raytrace_gaussians": 512,
        "log_every": max(1, iterations // 20),
        "checkpoint_every": max(1, iterations // 2),
    }


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
    try:
        if kind is int:
            number = float(text)
            if not number.is_integer():
                raise ValueError
            return int(number)
        if kind is float:
            return float(text)
    except ValueError as exc:
        raise ValueError(f"config key '{key}' expects {kind.__name__}, got '{text}'") from exc
    return text


def _checked(key: str, value: Any) -> Any:
    types = field_types()
    if key not in types:
        raise ValueError(f"unknown config key '{key}'")
    kind = types[key]
    if isinstance(value, str) and kind is not str:
        return parse_value(key, value)
    if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
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
        try:
            loaded = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: invalid JSON ({exc})") from exc
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


def load_run_config(run: Path) -> TrainConfig:
    """The resolved configuration saved in a run folder (``config.json``)."""
    path = Path(run) / "config.json"
    if not path.is_file():
        raise ValueError(f"{run} is not a training run: {path} is missing")
    return make_config("diamond", overrides=json.loads(path.read_text()))
