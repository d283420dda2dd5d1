"""The run-level training job behind the CLI: train a run folder (evaluate and render: evaluation.run)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.regimes import select_regime
from diamond_sss.training.config import TrainConfig
from diamond_sss.training.overrides import make_config
from diamond_sss.training.run_folder import check_same_images
from diamond_sss.training.trainer import ImageSource, StepCallback, Trainer, TrainResult
from diamond_sss.utils.io import atomic_write_json


def train_run(data: Path, out: Path, config: TrainConfig, *, split: str = "train", regime: str = "all",
              resume: bool = False, show_progress: bool = True,
              extra_sources: Sequence[ImageSource] = (), on_step: StepCallback | None = None) -> TrainResult:
    """Select the regime's images, train with the resolved ``config``
    (:func:`~diamond_sss.training.overrides.make_config`), and record everything in ``out``.

    The run folder records ``config.json`` (``config``), ``regime.json`` (the chosen views, lights and
    images), ``data.json`` (where the data came from, and the digest of the images it trained on:
    :meth:`~diamond_sss.data.dataset.OLATDataset.content_hash`) and, when done, ``model.safetensors``. ``on_step`` is
    called after every step (the trainer's :data:`~diamond_sss.training.trainer.StepCallback`). Resuming a folder that
    trained on other images is refused (:func:`~diamond_sss.training.run_folder.check_same_images`).
    """
    dataset = OLATDataset(data, split, downscale=config.runtime.downscale)
    selection = select_regime(dataset, regime, config.schedule.seed)
    digest = dataset.content_hash(selection.observations)
    out = Path(out)
    if resume:
        check_same_images(out, data, regime, digest)
    sources = [ImageSource(dataset.subset(selection.observations), 1.0), *extra_sources]
    trainer = Trainer(config, sources, out, show_progress=show_progress)  # refuses what cannot run, writes nothing
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "regime.json", selection.to_json())
    atomic_write_json(out / "data.json", {"data": str(Path(data).resolve()), "split": split, "regime": regime,
                                          "content_sha256": digest})
    return trainer.run(resume=resume, on_step=on_step)


def selected_images(data: Path, split: str, regime: str, seed: int) -> int:
    """How many training images ``regime`` selects from ``data``'s ``split`` under ``seed`` (reads the transforms,
    no image)."""
    return len(select_regime(OLATDataset(data, split), regime, seed).observations)


def train_from_preset(data: Path, out: Path, *, preset: str = "diamond", overrides: dict[str, Any] | None = None,
                      config_file: Path | None = None, sets: Sequence[str] = (), **options: Any) -> TrainResult:
    """:func:`train_run` with the configuration resolved from ``preset``, ``config_file``, ``overrides`` and ``sets``
    (:func:`~diamond_sss.training.overrides.make_config`); ``options``: :func:`train_run`'s keywords."""
    return train_run(data, out, make_config(preset, overrides=overrides, config_file=config_file, sets=sets),
                     **options)
