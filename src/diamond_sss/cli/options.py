"""Command-line options shared by several subcommands (no torch: ``diamond-sss --help`` imports this)."""

from __future__ import annotations

from typing import Annotated

import tyro

SetArg = Annotated[list[str], tyro.conf.UseAppendAction,
                   tyro.conf.arg(name="set", help="override a config key: --set key=value, the key dotted "
                                                  "(losses.lambda_dssim) or flat (lambda_dssim); every key, its "
                                                  "default and meaning: diamond-sss config")]
"""``--set key=value`` (repeatable), parsed by :func:`diamond_sss.training.overrides.parse_sets`."""
