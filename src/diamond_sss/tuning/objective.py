"""The objective of a trial: train a short reconstruction, report validation PSNR to the pruner.

Each trial resolves ``preset`` + fixed ``overrides`` + the sampled parameters (schedule keys scaled, see
:func:`~diamond_sss.training.config.scale_schedule`), trains with :meth:`Trainer.run` (no run folder: a trial
writes no checkpoint, log or model) for ``iterations`` steps and, from the trainer's step callback every
``report_every`` steps and at the end, reports the mean validation PSNR (dB) so a median pruner can stop it. A non-finite loss or render raises :class:`FloatingPointError`: the study records the
trial as failed (with the reason in the user attribute ``failure``) and goes on.
"""

from __future__ import annotations

import copy
import json
import math
import os
import socket
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import optuna

from diamond_sss.scene.model import RelightableScene
from diamond_sss.training.config import TrainConfig, canonical_key, scale_schedule
from diamond_sss.training.overrides import make_config
from diamond_sss.training.trainer import ImageSource, Trainer
from diamond_sss.tuning.space import (
    SEARCH_SPACE,
    ParamRange,
    default_schedule_scale,
    suggest_params,
)
from diamond_sss.tuning.validation import TuneData, validation_psnr


def worker_name() -> str:
    """``host:pid`` of this process (recorded on every trial it runs)."""
    return f"{socket.gethostname()}:{os.getpid()}"


@dataclass
class ObjectiveSettings:
    """How every trial of a study trains.

    Attributes:
        preset: base preset the sampled parameters are applied to.
        overrides: fixed TrainConfig values of every trial (e.g. ``num_gaussians``, ``device``).
        iterations: training steps of a trial.
        report_every: steps between validation PSNR reports (plus one at the end).
        schedule_scale: factor on iteration-valued keys; ``None``: ``iterations / schedule.iterations`` (10000).
    """

    preset: str = "diamond"
    overrides: dict[str, Any] = field(default_factory=dict)
    iterations: int = 500
    report_every: int = 100
    schedule_scale: float | None = None

    def __post_init__(self) -> None:
        if self.iterations <= 0:
            raise ValueError(f"iterations must be positive, got {self.iterations}")
        if self.report_every <= 0:
            raise ValueError(f"report_every must be positive, got {self.report_every}")
        if any(canonical_key(key) == "schedule.iterations" for key in self.overrides):
            raise ValueError("set the trial length with 'iterations', not in the overrides")

    @property
    def scale(self) -> float:
        return default_schedule_scale(self.iterations) if self.schedule_scale is None else self.schedule_scale

    def fingerprint(self, data: TuneData, space: Mapping[str, ParamRange] = SEARCH_SPACE) -> dict[str, Any]:
        """What every worker of one study must share (JSON-normalised; the device may differ)."""
        record = {
            "preset": self.preset, "iterations": self.iterations, "report_every": self.report_every,
            "schedule_scale": self.scale,
            "overrides": {k: v for k, v in self.overrides.items() if canonical_key(k) != "runtime.device"},
            "data": data.describe(), "space": {k: [r.low, r.high, r.log, r.step] for k, r in space.items()},
        }
        return json.loads(json.dumps(record))

    def trial_config(self, params: Mapping[str, Any]) -> TrainConfig:
        """The configuration a trial with sampled ``params`` (full-schedule units) trains with."""
        scaled = scale_schedule(params, self.scale, floors={})
        return make_config(self.preset, overrides={**self.overrides, **scaled, "iterations": self.iterations})


class Objective:
    """``objective(trial) -> validation PSNR (dB)`` for :meth:`optuna.Study.optimize` (to maximise).

    Args:
        data: training and validation images.
        settings: how trials train.
        space: the searched keys.
    """

    def __init__(self, data: TuneData, settings: ObjectiveSettings,
                 space: Mapping[str, ParamRange] = SEARCH_SPACE) -> None:
        self.data = data
        self.settings = settings
        self.space = space
        self._initial_scenes: dict[tuple, RelightableScene] = {}

    def __call__(self, trial: optuna.Trial) -> float:
        started = time.perf_counter()
        trial.set_user_attr("worker", worker_name())
        params = suggest_params(trial, self.space)
        cfg = self.settings.trial_config(params)
        try:
            value = self.train_and_score(trial, cfg)
        except FloatingPointError as exc:
            trial.set_user_attr("failure", str(exc))
            raise
        trial.set_user_attr("seconds", round(time.perf_counter() - started, 3))
        return value

    def initial_scene(self, trainer: Trainer) -> RelightableScene:
        """A copy of the trainer's initial scene, built once per worker (no searched key changes it)."""
        cfg = trainer.cfg
        key = (cfg.schedule.seed, cfg.gaussians.init, cfg.gaussians.count, cfg.shading.sss_width,
               cfg.shading.light_init, cfg.shading.mixed_precision, str(trainer.device))
        if key not in self._initial_scenes:
            self._initial_scenes[key] = trainer.build_scene()
        return copy.deepcopy(self._initial_scenes[key])

    def train_and_score(self, trial: optuna.Trial, cfg: TrainConfig) -> float:
        """Train ``cfg`` and report; raises ``TrialPruned`` when the pruner says so."""
        trainer = Trainer(cfg, [ImageSource(self.data.train)], None, show_progress=False)
        reported = {"value": math.nan}

        def report(done: int, scene: RelightableScene, terms: dict) -> bool:
            if done % self.settings.report_every and done != cfg.schedule.iterations:
                return False
            value = validation_psnr(scene, self.data.validation)
            if not math.isfinite(value):
                raise FloatingPointError(f"validation PSNR is {value} at step {done}")
            trial.report(value, done)
            trial.set_user_attr("gaussians", scene.gaussians.num_gaussians)
            if trial.should_prune():
                raise optuna.TrialPruned(f"pruned at step {done} with validation PSNR {value:.3f} dB")
            reported["value"] = value
            return False

        trainer.run(scene=self.initial_scene(trainer), on_step=report)
        return reported["value"]
