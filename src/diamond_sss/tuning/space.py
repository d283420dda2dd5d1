"""The search space of supplement Sec. A.3 (Fig. 5 / Tab. 4), declared once.

Every key is a :class:`~diamond_sss.training.config.TrainConfig` field by its flat name (the name of the
trial parameter in every study, old and new). Ranges bracket both columns of
Tab. 4 ("Original" = the ``sss3dgs`` preset, "Best" = the ``diamond`` preset), so both presets are points
of the space and can be enqueued as trials. Iteration-valued keys are given for the full schedule of
``schedule.iterations`` steps; a study with shorter trials scales them by
``iterations / schedule.iterations`` (:func:`~diamond_sss.training.config.scale_schedule`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import optuna

from diamond_sss.training.config import FIELDS, FLAT_KEYS, PRESETS, TrainConfig, canonical_key, field_types
from diamond_sss.training.overrides import make_config

ORIGINAL_PRESET = "sss3dgs"
BEST_PRESET = "diamond"


@dataclass(frozen=True)
class ParamRange:
    """A searched hyperparameter: ``[low, high]``, log-uniform when ``log``; ``step`` on the int grid."""

    low: float
    high: float
    log: bool = False
    step: int | None = None

    def distribution(self, kind: type) -> optuna.distributions.BaseDistribution:
        """The Optuna distribution of a field of Python type ``kind`` (int or float)."""
        if kind is int:
            return optuna.distributions.IntDistribution(int(self.low), int(self.high), log=self.log,
                                                        step=self.step or 1)
        return optuna.distributions.FloatDistribution(self.low, self.high, log=self.log)


SEARCH_SPACE: dict[str, ParamRange] = {
    "lambda_dssim": ParamRange(0.1, 0.6),
    "lambda_lpips": ParamRange(0.05, 0.3),
    "lambda_normal": ParamRange(0.01, 0.06, log=True),
    "lambda_visibility": ParamRange(0.005, 0.02, log=True),
    "lambda_incident_light": ParamRange(0.005, 0.03, log=True),
    "lambda_base_color": ParamRange(0.001, 0.01, log=True),
    "lambda_base_color_smooth": ParamRange(0.002, 0.02, log=True),
    "lambda_metallic_smooth": ParamRange(0.001, 0.01, log=True),
    "lambda_roughness_smooth": ParamRange(0.001, 0.01, log=True),
    "lambda_subsurfacedness_smooth": ParamRange(0.001, 0.01, log=True),
    "densification_interval": ParamRange(50, 300, step=10),
    "opacity_reset_interval": ParamRange(500, 4000, step=500),
    "densify_from_iter": ParamRange(100, 1000, step=100),
    "densify_until_iter": ParamRange(5000, 20000, step=1000),
    "densify_grad_threshold": ParamRange(0.0001, 0.002, log=True),
}

def distributions(
        space: Mapping[str, ParamRange] = SEARCH_SPACE) -> dict[str, optuna.distributions.BaseDistribution]:
    """Optuna distributions of ``space`` by key (types from ``TrainConfig``); unknown keys are errors."""
    types = field_types()
    unknown = sorted(set(space) - set(FLAT_KEYS) - set(FIELDS))
    if unknown:
        raise ValueError(f"search space keys are not TrainConfig fields: {unknown}")
    return {key: spec.distribution(types[canonical_key(key)]) for key, spec in space.items()}


def suggest_params(trial: optuna.Trial, space: Mapping[str, ParamRange] = SEARCH_SPACE) -> dict[str, Any]:
    """Sample (or take the enqueued values of) every key of ``space`` for ``trial``."""
    params: dict[str, Any] = {}
    for key, dist in distributions(space).items():
        if isinstance(dist, optuna.distributions.IntDistribution):
            params[key] = trial.suggest_int(key, dist.low, dist.high, step=dist.step, log=dist.log)
        else:
            params[key] = trial.suggest_float(key, dist.low, dist.high, log=dist.log)
    return params


def preset_params(preset: str, space: Mapping[str, ParamRange] = SEARCH_SPACE) -> dict[str, Any]:
    """The values a preset gives the searched keys (a column of Tab. 4)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset '{preset}'; presets: {sorted(PRESETS)}")
    config = make_config(preset)
    return {key: config.get(key) for key in space}


def default_schedule_scale(iterations: int) -> float:
    """``iterations / schedule.iterations``: the factor that maps Tab. 4 schedules onto shorter trials."""
    if iterations <= 0:
        raise ValueError(f"iterations must be positive, got {iterations}")
    return iterations / TrainConfig().schedule.iterations
