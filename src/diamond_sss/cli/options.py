"""Command-line options shared by several subcommands, and options derived from config dataclasses (no torch:
``diamond-sss --help`` imports this)."""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Collection, Mapping
from typing import Annotated, Any

import tyro

SetArg = Annotated[list[str], tyro.conf.UseAppendAction,
                   tyro.conf.arg(name="set", help="override a config key: --set key=value, the key dotted "
                                                  "(losses.lambda_dssim) or flat (lambda_dssim); every key, its "
                                                  "default and meaning: diamond-sss config")]
"""``--set key=value`` (repeatable), parsed by :func:`diamond_sss.training.overrides.parse_sets`."""


def given_overrides(**options: object) -> dict:
    """The config keys among ``options`` the user gave (not None): a flag left out keeps the value of
    ``--config`` or the preset, so each default lives once, in the config."""
    return {key: value for key, value in options.items() if value is not None}


def options_of(config: type, exclude: Collection[str] = (), include: Collection[str] | None = None) -> type:
    """A dataclass of ``config``'s fields (those in ``include`` if given, but ``exclude``) for tyro: the same
    names, types and defaults, with each field's ``metadata["help"]`` or else its entry in the ``Attributes:``
    of ``config``'s docstring as help text, so that a default and its meaning live once, in ``config``. Pass it
    as an ``Annotated[..., tyro.conf.OmitArgPrefixes]`` parameter to keep flat flag names; :func:`config_from`
    turns the parsed options back into ``config``."""
    hints = typing.get_type_hints(config)
    specs = [(f.name, Annotated[hints[f.name], tyro.conf.arg(help=f.metadata.get("help") or None)],
              dataclasses.field(default=f.default, default_factory=f.default_factory))
             for f in dataclasses.fields(config)
             if f.name not in exclude and (include is None or f.name in include)]
    options = dataclasses.make_dataclass(f"{config.__name__}Options", specs)
    options.__doc__ = config.__doc__
    return options


def config_from(config: type, options: Any, **rest: Any) -> Any:
    """``config`` built from parsed :func:`options_of` ``options`` and the ``rest`` of its fields."""
    return config(**{f.name: getattr(options, f.name) for f in dataclasses.fields(options)}, **rest)


PresetArg = Annotated[str, tyro.conf.arg(help=(
    "auto (the diamond preset with the settings measured for the run's length and capture, "
    "training.config.short_schedule, what --short-run gave before it became the default; at 3,000 steps on a dense "
    "capture 5.5 dB over the diamond preset's schedule, DIAMOND-SSS issue 60) | diamond (supplement Tab. 3 / "
    "Tab. 4 'Best', also named paper) | sss3dgs (Tab. 4 'Original'); a named preset keeps its own schedule, scaled "
    "to --iterations"))]
"""``--preset`` of ``train``, ``run`` and ``config``."""


def schedule_overrides(preset: str, iterations: int | None, *, keep_schedule: bool = False, short_run: bool = False,
                       dense: bool = False, pipeline_final: bool = False, given: Mapping[str, Any] | None = None,
                       fixed: Collection[str] = ()) -> tuple[str, dict[str, Any], str | None]:
    """The preset that ``preset`` resolves to, the config overrides (dotted keys) of ``--iterations``,
    ``--keep-schedule`` and ``--short-run``, and a line saying what they changed (``None`` when nothing was asked).

    ``preset`` :data:`~diamond_sss.training.config.AUTO_PRESET` (the command line's default) resolves to ``diamond``
    with the short-run settings, as ``short_run`` gives them to a named preset:
    :func:`diamond_sss.training.overrides.short_run_overrides` for ``iterations`` steps (default
    :data:`~diamond_sss.training.config.SHORT_SCHEDULE`'s 1000; a ``dense`` capture's or a ``pipeline_final``
    reconstruction's settings with them), less the ``given`` keys (the checked values of ``--config``). Otherwise the
    step-valued keys of ``preset`` (+ ``given``) scaled to ``iterations``
    (:func:`~diamond_sss.training.overrides.scaled_run_schedule`; the ``fixed`` keys, those of ``--set``, keep their
    value), or with ``keep_schedule`` only the step count changed.
    """
    from diamond_sss.training.config import AUTO_PRESET, SHORT_SCHEDULE
    from diamond_sss.training.overrides import scaled_run_schedule, short_run_overrides

    if iterations is not None and iterations <= 0:
        raise ValueError(f"--iterations must be a positive number of training steps, got {iterations}")
    auto = preset == AUTO_PRESET
    if short_run and keep_schedule:
        raise ValueError("--keep-schedule keeps the preset's schedule and --short-run brings its own: give one of them")
    if auto and keep_schedule:
        raise ValueError("--keep-schedule keeps a named preset's schedule (--preset diamond | sss3dgs); the default "
                         "preset auto brings the short-run schedule, scaled to --iterations")
    if auto or short_run:
        steps = SHORT_SCHEDULE["iterations"] if iterations is None else iterations
        settings = short_run_overrides(steps, dense=dense, pipeline_final=pipeline_final, given=set(given or {}))
        listed = ", ".join(f"{key}={value}" for key, value in settings.items() if key != "schedule.iterations")
        said = (f"{'preset auto = diamond with the ' if auto else ''}short-run settings for {steps} steps "
                f"(training.config.short_schedule): {listed}")
        return "diamond" if auto else preset, settings, said
    if iterations is None:
        return preset, {}, None
    if keep_schedule:
        return preset, {"schedule.iterations": iterations}, None
    scaled, changes = scaled_run_schedule(preset, iterations, given=given, fixed=fixed)
    listed = ", ".join(f"{key} {old}->{new}" for key, (old, new) in changes.items())
    return preset, scaled, (f"schedule scaled to {iterations} steps (--keep-schedule keeps the preset's): "
                            f"{listed or 'no change'}")
