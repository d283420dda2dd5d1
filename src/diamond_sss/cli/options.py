"""Command-line options shared by several subcommands, and options derived from config dataclasses (no torch:
``diamond-sss --help`` imports this)."""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Collection
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
