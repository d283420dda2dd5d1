"""Resolve a :class:`~diamond_sss.training.config.TrainConfig` from a preset and overrides.

Overrides come from a JSON ``--config FILE``, a mapping (``overrides=``) or ``--set key=value`` strings. A
mapping may be nested (``{"losses": {"lambda_dssim": 0.3}}``, the layout of a run's ``config.json``), dotted
(``{"losses.lambda_dssim": 0.3}``) or flat (``{"lambda_dssim": 0.3}``, the layout of runs and tuning studies
made before the groups), or a mix. The resolved configuration is saved in the run, nested.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

from diamond_sss.errors import DataError
from diamond_sss.losses.photometric import PIXEL_ERRORS
from diamond_sss.training.config import (
    AUTO_PRESET,
    FIELDS,
    GROUPS,
    PIPELINE_KEYS,
    PRESETS,
    TrainConfig,
    canonical_key,
    field_types,
    schedule_for,
    short_schedule,
)
from diamond_sss.utils.compiling import COMPILE_BACKENDS
from diamond_sss.utils.io import read_json


def parse_value(key: str, text: str) -> Any:
    """Parse the string ``text`` as the type of (dotted or flat) ``key``; clear errors for unknown keys and
    bad values."""
    kind = field_types()[canonical_key(key)]
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
    kind = field_types()[canonical_key(key)]
    if isinstance(value, str) and kind is not str:
        return parse_value(key, value)
    if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return _finite(key, float(value))
    if kind is int and isinstance(value, float) and value.is_integer():
        return int(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ValueError(f"config key '{key}' expects {kind.__name__}, got {value!r}")
    return value


def checked_values(values: Mapping[str, Any]) -> dict[str, Any]:
    """Dotted key -> checked value of a nested, dotted or flat mapping of config keys (later keys win)."""
    checked: dict[str, Any] = {}
    for key, value in values.items():
        if key in GROUPS and isinstance(value, Mapping):
            checked.update(checked_values({f"{key}.{name}": inner for name, inner in value.items()}))
        else:
            checked[canonical_key(key)] = _checked(key, value)
    return checked


def parse_sets(sets: Sequence[str]) -> dict[str, Any]:
    """``["key=value", ...]`` (as given to ``--set``; dotted or flat keys, kept as given) -> typed values."""
    parsed: dict[str, Any] = {}
    for item in sets:
        if "=" not in item:
            raise ValueError(f"--set expects key=value, got '{item}'")
        key, text = item.split("=", 1)
        parsed[key.strip()] = parse_value(key.strip(), text)
    return parsed


def with_values(config: TrainConfig, values: Mapping[str, Any]) -> TrainConfig:
    """A copy of ``config`` with the checked ``values`` (by dotted key) applied; ``config`` is unchanged."""
    groups: dict[str, dict[str, Any]] = {}
    for dotted, value in values.items():
        group, name = dotted.split(".")
        groups.setdefault(group, {})[name] = value
    config = copy.deepcopy(config)
    return dataclasses.replace(config, **{group: dataclasses.replace(getattr(config, group), **changed)
                                          for group, changed in groups.items()})


def config_file_values(config_file: Path) -> dict[str, Any]:
    """Dotted key -> checked value of the JSON object of config keys in ``config_file`` (``--config``); errors
    name the file."""
    path = Path(config_file)
    if not path.is_file():
        raise ValueError(f"config file not found: {path}")
    loaded = read_json(path)
    try:
        if isinstance(loaded, dict):
            return checked_values(loaded)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    raise ValueError(f"{path}: expected a JSON object of config keys")


def make_config(preset: str = "diamond", overrides: Mapping[str, Any] | None = None,
                config_file: Path | None = None, sets: Sequence[str] = ()) -> TrainConfig:
    """Resolve a configuration: preset, then ``config_file`` (JSON object), then ``overrides``, then ``sets``.

    ``sets`` are ``"key=value"`` strings as given to ``--set``.
    """
    if preset == AUTO_PRESET:
        raise ValueError(f"preset '{AUTO_PRESET}' is the command line's: it resolves to diamond with "
                         "short_schedule(iterations, dense) as overrides; name a preset here: "
                         f"{sorted(PRESETS)}")
    if preset not in PRESETS:
        raise ValueError(f"unknown preset '{preset}'; presets: {sorted(PRESETS)}")
    values = config_file_values(config_file) if config_file is not None else {}
    values.update(checked_values(overrides or {}))
    values.update(checked_values(parse_sets(sets)))
    return validated(with_values(PRESETS[preset], values))


POSITIVE_KEYS = ("schedule.iterations", "schedule.batch_size", "gaussians.count", "gaussians.max_count",
                 "shading.sss_width", "shading.sss_light_depth_every", "runtime.checkpoint_every", "runtime.log_every",
                 "runtime.image_log_every", "densify.refine_every", "densify.reset_every", "raytrace.every",
                 "raytrace.gaussians", "multiview.target_downscale", "multiview.pairs_per_step",
                 "multiview.pixels_per_pair", "multiview.nearest_k")
"""Sizes and step periods that have no 'off' value (a loss or a process is turned off by its weight or flag)."""

NON_NEGATIVE_KEYS = ("shading.sss_light_depth", "shading.sss_position_freqs", "lr.sss_warmup_steps",
                     "lr.position_delay_steps", "runtime.keep_checkpoints", "runtime.cpu_threads",
                     "densify.refine_start_iter", "densify.refine_stop_iter", "densify.grow_grad2d",
                     "densify.grow_scale3d", "raytrace.directions", "multiview.occlusion_tol",
                     "multiview.charbonnier_eps", "multiview.depth_tolerance")
"""Sizes, step counts and tolerances where 0 means off or none (for ``runtime.keep_checkpoints``: no limit; for
``runtime.cpu_threads``: torch's default), besides the loss weights and learning rates."""

FRACTIONS = {"losses.lambda_dssim": "[0, 1]", "densify.prune_opa": "[0, 1]", "multiview.sil_threshold": "[0, 1]",
             "multiview.sil_tolerance": "(0, 1]", "multiview.start_fraction": "[0, 1)",
             "schedule.average_last": "[0, 1)"}
"""Shares, opacities and silhouette values: the interval each lies in (``(`` and ``)`` leave the end out)."""

CHOICES = {"gaussians.init": ("auto", "ply", "hull", "random"), "gaussians.hull_masks": ("real", "all"),
           "losses.photometric_space": ("linear", "srgb"),
           "losses.photometric_error": tuple(PIXEL_ERRORS), "multiview.target_mode": ("nearest-k", "random"),
           "multiview.source_gradient": ("blend", "centres"),
           "runtime.compile": COMPILE_BACKENDS,
           "shading.light_falloff": ("none", "inverse_square")}


def _within(value: float, interval: str) -> bool:
    """Whether ``value`` lies in ``interval``, one of :data:`FRACTIONS`' (within [0, 1])."""
    above = value > 0 if interval[0] == "(" else value >= 0
    below = value < 1 if interval[-1] == ")" else value <= 1
    return above and below


def validated(config: TrainConfig) -> TrainConfig:
    """``config`` once every value is checked: values that cannot work raise ``ValueError`` naming the key, what
    it expects and what was given, before a run writes anything."""
    for key in POSITIVE_KEYS:
        if config.get(key) <= 0:
            raise ValueError(f"config key '{key}' must be positive, got {config.get(key)}")
    non_negative = [f"losses.{f.name}" for f in dataclasses.fields(config.losses) if f.name.startswith("lambda_")]
    non_negative += [f"lr.{f.name}" for f in dataclasses.fields(config.lr) if f.type in (float, "float")]
    non_negative += NON_NEGATIVE_KEYS
    for key in non_negative:
        if not config.get(key) >= 0:
            raise ValueError(f"config key '{key}' must be >= 0, got {config.get(key)}")
    zero = [key for key in ("lr.position_init", "lr.position_final") if config.get(key) == 0]
    if len(zero) == 1:  # the schedule is log-linear between the two: both > 0, or both 0 to freeze the positions
        raise ValueError(f"config key '{zero[0]}' must be positive when the other position rate is, got 0.0")
    for key, choices in CHOICES.items():
        if config.get(key) not in choices:
            raise ValueError(f"config key '{key}' must be {'|'.join(choices)}, got '{config.get(key)}'")
    device = config.runtime.device
    if device not in ("auto", "cpu", "cuda") and not device.startswith("cuda:"):
        raise ValueError(f"config key 'runtime.device' must be auto|cpu|cuda[:i], got '{device}'")
    for key, interval in FRACTIONS.items():
        if not _within(config.get(key), interval):
            raise ValueError(f"config key '{key}' must be in {interval}, got {config.get(key)}")
    if config.runtime.downscale < 1:
        raise ValueError(f"config key 'runtime.downscale' must be >= 1, got {config.runtime.downscale}")
    return config


def describe_config(preset: str = "diamond", overrides: Mapping[str, Any] | None = None
                    ) -> list[tuple[str, str, Any, str]]:
    """``(dotted key, flat name, value, meaning)`` of every :class:`TrainConfig` field under ``preset`` and
    ``overrides``."""
    config = make_config(preset, overrides=overrides)
    return [(key, f.metadata.get("flat", f.name), config.get(key), f.metadata["help"])
            for key, f in FIELDS.items()]


def rescheduled(config: TrainConfig, iterations: int) -> dict[str, Any]:
    """Overrides (dotted keys) that make ``config`` a run of ``iterations`` steps: its step-valued keys scaled by
    ``iterations / config.schedule.iterations`` (:func:`~diamond_sss.training.config.schedule_for`)."""
    return schedule_for({key: config.get(key) for key in FIELDS}, iterations)


def scaled_run_schedule(preset: str, iterations: int, given: Mapping[str, Any] | None = None,
                        fixed: Collection[str] = ()) -> tuple[dict[str, Any], dict[str, tuple[Any, Any]]]:
    """Overrides (dotted keys) that scale the schedule of ``preset`` (+ ``given``, the values of a ``--config``
    file: :func:`config_file_values`) to ``iterations`` steps, and the changed keys as ``key -> (before, after)``.
    The ``fixed`` keys (dotted or flat: those ``--set`` gives) keep their value."""
    config = make_config(preset, overrides=given)
    base = {key: config.get(key) for key in FIELDS}
    fixed = {canonical_key(key) for key in fixed}
    scaled = {key: value for key, value in rescheduled(config, iterations).items() if key not in fixed}
    changes = {key: (base[key], value) for key, value in scaled.items()
               if key != "schedule.iterations" and value != base[key]}
    return scaled, changes


def short_run_overrides(iterations: int, *, dense: bool = False, pipeline_final: bool = False,
                        given: Collection[str] = ()) -> dict[str, Any]:
    """:func:`~diamond_sss.training.config.short_schedule` (the settings measured for runs of 1,000 to 10,000 steps
    on 64-px captures: the demo's and the benchmarks') as dotted overrides, less the ``given`` keys (dotted: those of
    a ``--config`` file, :func:`config_file_values`), so that the file's values come after the short-run settings
    (and ``--set``'s after both)."""
    settings = checked_values(short_schedule(iterations, dense=dense, pipeline_final=pipeline_final))
    return {key: value for key, value in settings.items() if key not in given}


def without_pipeline_keys(values: Mapping[str, Any]) -> dict[str, Any]:
    """A nested, dotted or flat mapping of config keys without the
    :data:`~diamond_sss.training.config.PIPELINE_KEYS` that earlier runs recorded."""
    kept = {}
    for key, value in values.items():
        if key in GROUPS and isinstance(value, Mapping):
            kept[key] = {name: inner for name, inner in value.items() if f"{key}.{name}" not in PIPELINE_KEYS}
        elif key not in PIPELINE_KEYS and key not in PIPELINE_KEYS.values():
            kept[key] = value
    return kept


def load_run_config(run: Path) -> TrainConfig:
    """The resolved configuration saved in a run folder (``config.json``, nested or flat; a setting it records
    that is the pipeline's now, :data:`~diamond_sss.training.config.PIPELINE_KEYS`, left out)."""
    path = Path(run) / "config.json"
    if not path.is_file():
        raise ValueError(f"{run} is not a training run: {path} is missing")
    recorded = read_json(path)
    if not isinstance(recorded, dict):
        raise DataError(f"{path}: expected a JSON object of config keys")
    try:
        return validated(with_values(PRESETS["diamond"], checked_values(without_pipeline_keys(recorded))))
    except ValueError as exc:
        raise DataError(f"{path}: {exc}") from exc
