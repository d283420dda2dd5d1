"""Hyperparameter search (supplement Sec. A.3): search space, objective, study workers, Fig. 5 / Tab. 4."""

from __future__ import annotations

from diamond_sss.tuning.objective import Objective, ObjectiveSettings
from diamond_sss.tuning.report import best_config, save_parallel_coordinate, tab4_markdown, write_report
from diamond_sss.tuning.space import SEARCH_SPACE, ParamRange, preset_params, suggest_params
from diamond_sss.tuning.study import StudySettings, default_storage, open_study, run_worker
from diamond_sss.tuning.validation import TuneData, holdout_positions, load_tune_data, validation_psnr

__all__ = [
    "SEARCH_SPACE", "Objective", "ObjectiveSettings", "ParamRange", "StudySettings",
    "TuneData", "best_config", "default_storage", "holdout_positions", "load_tune_data", "open_study",
    "preset_params", "run_worker", "save_parallel_coordinate", "suggest_params", "tab4_markdown",
    "validation_psnr", "write_report",
]
