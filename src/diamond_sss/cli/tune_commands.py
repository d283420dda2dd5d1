"""``diamond-sss tune``: the hyperparameter search of supplement Sec. A.3 (one worker of a study)."""

from __future__ import annotations

from pathlib import Path

import tyro
from rich.console import Console

from diamond_sss.cli.options import SetArg, given_overrides


def tune(data: Path, out: Path, regime: str = "all", trials: int = 20, storage: str | None = None,
         study: str = "diamond-sss", split: str = "train", preset: str = "diamond", iterations: int = 500,
         report_every: int = 100, validation_images: int | None = None, schedule_scale: float | None = None,
         set_: SetArg = [], seed: int | None = None, worker: int = 0, device: str | None = None,  # noqa: B006
         timeout: float | None = None, heartbeat_interval: int = 60, pruner_startup_trials: int = 3,
         enqueue_presets: bool = True, report_only: bool = False) -> None:
    """Search the loss weights and densification schedule (Fig. 5 / Tab. 4) on your capture with Optuna.

    Each trial trains --iterations steps and is scored by PSNR on images held out of the regime's
    TRAINING images (never the test split), reported every --report-every steps to a median pruner
    (never at the first report). Writes to --out: parallel_coordinate.png (Fig. 5), tab4.md (original
    vs best), best_config.json (for `diamond-sss train --config`), best_trial.json and trials.csv.
    Several workers (machines) share one study when they get the same --storage URL (PostgreSQL) and
    --study name; --trials is the total. A trial whose worker dies is re-run by another worker.

    Args:
        data: data folder holding transforms_<split>.json.
        out: output folder (default storage study.db, plot, table, best configuration).
        regime: capture regime whose images the trials train on (validation images are held out of them).
        trials: total trials of the study, shared by all its workers (the two enqueued presets included).
        storage: SQLAlchemy URL, e.g. postgresql://user:password@host:5432/db; default sqlite in --out.
        study: study name (workers of one study use the same name and storage).
        split: training split.
        preset: base preset the searched values are applied to.
        iterations: training steps of one trial.
        report_every: steps between validation PSNR reports to the pruner.
        validation_images: held-out images (default: 10% of the selection, 1 to 8).
        schedule_scale: factor on the iteration-valued keys (default iterations / 10000).
        seed: seed of the regime, the validation split, training and the sampler (schedule.seed; default: the
            preset's).
        worker: index of this worker (give each worker of a shared study its own).
        device: auto | cpu | cuda (runtime.device; default: the preset's).
        timeout: stop starting trials after this many seconds.
        heartbeat_interval: seconds between heartbeats; a trial silent for twice this is re-queued.
        pruner_startup_trials: completed trials before the median pruner starts pruning.
        enqueue_presets: the study's creator enqueues the sss3dgs and diamond presets as its first trials.
        report_only: only write the outputs of the study as it stands.
    """
    try:
        import optuna  # noqa: F401
    except ImportError as exc:
        raise ValueError("diamond-sss tune needs Optuna: pip install 'diamond-sss[tune]'") from exc
    from diamond_sss.training.config import canonical_key
    from diamond_sss.training.overrides import make_config, parse_sets
    from diamond_sss.tuning.objective import ObjectiveSettings
    from diamond_sss.tuning.run import run_study
    from diamond_sss.tuning.space import SEARCH_SPACE
    from diamond_sss.tuning.study import StudySettings, default_storage
    from diamond_sss.tuning.validation import load_tune_data

    overrides = given_overrides(seed=seed, device=device)
    searched = {canonical_key(key) for key in SEARCH_SPACE}
    for key, value in parse_sets(set_).items():
        if canonical_key(key) in searched or canonical_key(key) == "schedule.iterations":
            reason = "searched" if canonical_key(key) in searched else "set by --iterations"
            raise ValueError(f"--set {key}: '{key}' is {reason}")
        overrides[key] = value
    objective_settings = ObjectiveSettings(preset=preset, overrides=overrides, iterations=iterations,
                                           report_every=report_every, schedule_scale=schedule_scale)
    trial_config = make_config(preset, overrides=overrides)
    seed = trial_config.schedule.seed
    tune_data = load_tune_data(data, split=split, regime=regime, seed=seed,
                               validation_images=validation_images, downscale=trial_config.runtime.downscale)
    study_settings = StudySettings(storage=storage or default_storage(out), study_name=study, seed=seed,
                                   worker=worker, pruner_startup_trials=pruner_startup_trials,
                                   pruner_warmup_steps=report_every + 1,
                                   heartbeat_interval=heartbeat_interval, enqueue_presets=enqueue_presets)
    result = run_study(tune_data, out, objective_settings, study_settings, trials=trials, timeout=timeout,
                       report_only=report_only)
    console = Console(soft_wrap=True)
    if not report_only:
        console.print(f"worker {worker} ran trials {result.ran}")
    best = result.study.best_trial
    console.print(f"best: trial {best.number}, validation PSNR {best.value:.3f} dB")
    for name, path in result.paths.items():
        console.print(f"  {name}: {path}")


if __name__ == "__main__":
    tyro.cli(tune)
