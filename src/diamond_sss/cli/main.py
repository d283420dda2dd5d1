"""The ``diamond-sss`` command line: one subcommand per job, each a typed function (tyro)."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable

import tyro

from diamond_sss.cli.data_commands import info, regimes, subset
from diamond_sss.cli.demo import demo
from diamond_sss.cli.model_commands import blend_models
from diamond_sss.cli.nvs_commands import convert_free3d, finetune_nvs, nvs
from diamond_sss.cli.pipeline_commands import run
from diamond_sss.cli.relight_commands import finetune_relight, relight
from diamond_sss.cli.repair_commands import repair_data, repair_train
from diamond_sss.cli.synth_commands import synth
from diamond_sss.cli.train_commands import ablate, config, evaluate, export, render, train, view
from diamond_sss.cli.tune_commands import tune
from diamond_sss.errors import DataError


def commands() -> dict[str, Callable[..., None]]:
    """The subcommands, by name."""
    return {"demo": demo, "info": info, "regimes": regimes, "subset": subset, "synth": synth, "config": config,
            "train": train, "eval": evaluate, "render": render, "export": export, "view": view, "ablate": ablate,
            "run": run, "tune": tune, "finetune-relight": finetune_relight, "relight": relight,
            "finetune-nvs": finetune_nvs, "nvs": nvs, "convert-free3d": convert_free3d, "blend-models": blend_models,
            "repair-data": repair_data, "repair-train": repair_train}


def configure_logging() -> None:
    """Warnings and errors as one ``LEVEL: message`` line each on stderr (no-op if logging is configured)."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s: %(message)s")


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``diamond-sss`` console script."""
    configure_logging()
    try:
        tyro.extras.subcommand_cli_from_dict(commands(), args=argv, prog="diamond-sss")
    except (DataError, FileNotFoundError, ValueError, FloatingPointError) as exc:
        print(f"diamond-sss: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from exc


if __name__ == "__main__":
    main()
