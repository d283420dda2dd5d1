"""What a study produces: the parallel-coordinate plot (Fig. 5), the original-vs-best table (Tab. 4),
the best configuration for ``diamond-sss train --config``, and a CSV of every trial."""

from __future__ import annotations

import csv
import io
import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import optuna
from optuna.trial import FrozenTrial, TrialState

from diamond_sss.training.config import canonical_key
from diamond_sss.training.overrides import make_config
from diamond_sss.tuning.space import BEST_PRESET, ORIGINAL_PRESET, SEARCH_SPACE, ParamRange, preset_params
from diamond_sss.utils.io import atomic_write, atomic_write_json, atomic_write_text

# keys of a trial's configuration that belong to the run, not to the method (left to the preset / CLI)
RUN_KEYS = ("schedule.iterations", "schedule.seed", "runtime.device", "runtime.checkpoint_every",
            "runtime.log_every", "runtime.image_log_every", "runtime.lpips_weights")


def format_value(value: Any) -> str:
    """Ints as they are; floats with 3 significant digits (``0.492``, ``0.0002``); missing as ``-``."""
    if value is None:
        return "-"
    if isinstance(value, (bool, int)):
        return str(value)
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    return f"{value:.3g}"


def comparison_table(columns: Sequence[tuple[str, Mapping[str, Any]]], keys: Sequence[str],
                     scores: Sequence[float | None] | None = None) -> str:
    """A Markdown table: one row per key, one column per ``(title, values)``; a PSNR row when ``scores``."""
    lines = ["| Hyperparameter | " + " | ".join(title for title, _ in columns) + " |",
             "|---|" + "---:|" * len(columns)]
    for key in keys:
        cells = [format_value(values.get(key)) for _, values in columns]
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    if scores is not None:
        cells = ["-" if s is None else f"{s:.2f}" for s in scores]
        lines.append("| validation PSNR (dB) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def completed_trials(study: optuna.Study) -> list[FrozenTrial]:
    return study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))


def preset_trial(study: optuna.Study, preset: str) -> FrozenTrial | None:
    """The best completed trial of an enqueued preset (``user_attrs['preset']``), if any."""
    trials = [t for t in completed_trials(study) if t.user_attrs.get("preset") == preset]
    return max(trials, key=lambda t: t.value) if trials else None


def tab4_markdown(study: optuna.Study, space: Mapping[str, ParamRange] = SEARCH_SPACE) -> str:
    """Tab. 4 for this study: the ``sss3dgs`` preset (Original), the study's best trial, the paper's Best."""
    best = study.best_trial
    original, paper = preset_trial(study, ORIGINAL_PRESET), preset_trial(study, BEST_PRESET)
    columns = [("Original (sss3dgs)", preset_params(ORIGINAL_PRESET, space)),
               (f"Best (trial {best.number})", best.params),
               ("Paper best (diamond)", preset_params(BEST_PRESET, space))]
    scores = [None if t is None else t.value for t in (original, best, paper)]
    settings = study.user_attrs.get("settings", {})
    validation = settings.get("data", {}).get("validation_images", "?")
    header = (f"Study `{study.study_name}`: {len(completed_trials(study))} completed of {len(study.trials)} "
              f"trials on the `{settings.get('preset', '?')}` preset; validation PSNR on {validation} "
              f"held-out training images after {settings.get('iterations', '?')} steps (schedule keys "
              f"scaled by {format_value(settings.get('schedule_scale'))}; the table gives full-schedule "
              "values).\n\n")
    return header + comparison_table(columns, list(space), scores)


def best_config(study: optuna.Study, space: Mapping[str, ParamRange] = SEARCH_SPACE) -> dict[str, Any]:
    """The best trial's configuration as a flat JSON object for ``diamond-sss train --config``.

    It holds the study's preset and fixed overrides (without run keys such as ``iterations``) and the best
    searched values in full-schedule units, so it trains the same method whatever ``--preset`` is given.
    """
    settings = study.user_attrs.get("settings", {})
    overrides = {k: v for k, v in settings.get("overrides", {}).items() if canonical_key(k) not in RUN_KEYS}
    best = {key: study.best_trial.params[key] for key in space if key in study.best_trial.params}
    config = make_config(settings.get("preset", BEST_PRESET), overrides={**overrides, **best})
    return {key: value for key, value in config.flat().items() if canonical_key(key) not in RUN_KEYS}


def save_parallel_coordinate(study: optuna.Study, path: Path,
                             space: Mapping[str, ParamRange] = SEARCH_SPACE) -> Path:
    """Fig. 5: one polyline per completed trial over the searched parameters, coloured by validation PSNR."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        axes = optuna.visualization.matplotlib.plot_parallel_coordinate(
            study, params=list(space), target_name="validation PSNR (dB)")
    figure = axes.get_figure()
    figure.set_size_inches(max(12.0, 1.1 * len(space)), 6.0)
    axes.set_title(f"Study '{study.study_name}': one line per completed trial, coloured by validation PSNR",
                   pad=18)
    figure.tight_layout()
    atomic_write(path, lambda tmp: figure.savefig(tmp, format="png", dpi=100))
    plt.close(figure)
    return Path(path)


def trials_csv(trials: Sequence[FrozenTrial], keys: Sequence[str]) -> str:
    """One row per trial: number, state, value, worker, preset, retried trial, failure, parameters."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["number", "state", "value", "worker", "preset", "retry_of", "failure", *keys])
    for t in trials:
        writer.writerow([t.number, t.state.name, "" if t.value is None else f"{t.value:.4f}",
                         t.user_attrs.get("worker", ""), t.user_attrs.get("preset", ""),
                         t.system_attrs.get("failed_trial", ""), t.user_attrs.get("failure", ""),
                         *[t.params.get(k, "") for k in keys]])
    return buffer.getvalue()


def write_report(study: optuna.Study, out: Path,
                 space: Mapping[str, ParamRange] = SEARCH_SPACE) -> dict[str, Path]:
    """``parallel_coordinate.png``, ``tab4.md``, ``best_config.json``, ``best_trial.json`` and ``trials.csv``.

    Raises ``ValueError`` while the study has no completed trial.
    """
    if not completed_trials(study):
        raise ValueError(f"study '{study.study_name}' has no completed trial yet: nothing to report")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    best = study.best_trial
    paths = {
        "plot": save_parallel_coordinate(study, out / "parallel_coordinate.png", space),
        "table": atomic_write_text(out / "tab4.md", tab4_markdown(study, space)),
        "config": atomic_write_json(out / "best_config.json", best_config(study, space)),
        "best_trial": atomic_write_json(out / "best_trial.json", {
            "study": study.study_name, "number": best.number, "value": best.value, "params": best.params,
            "user_attrs": best.user_attrs, "settings": study.user_attrs.get("settings", {})}),
        "trials": atomic_write_text(out / "trials.csv", trials_csv(study.trials, list(space))),
    }
    return {key: Path(path) for key, path in paths.items()}
