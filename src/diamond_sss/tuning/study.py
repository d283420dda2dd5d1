"""Open a study on any SQLAlchemy storage and run one worker of it.

One machine: the default storage is an SQLite file in the output folder. Several machines: give every
worker the same PostgreSQL URL and study name; they share the trial budget. Workers send heartbeats;
a trial whose worker died is failed once its heartbeat is older than the grace period and re-queued
with the same parameters (Optuna's retry callback), and a live or restarted worker runs the copy.
The creator of a study enqueues the two presets of Tab. 4 as its first trials, so the study measures
"Original" and the paper's "Best" on the same data.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import optuna
import sqlalchemy
from optuna.trial import FrozenTrial, TrialState

from diamond_sss.tuning.space import BEST_PRESET, ORIGINAL_PRESET, preset_params

SCHEMA_ATTEMPTS = 5
FINISHED_OR_ACTIVE = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING, TrialState.WAITING)


@dataclass
class StudySettings:
    """Where the study lives and how it samples, prunes and survives workers that die.

    Attributes:
        storage: SQLAlchemy URL (``sqlite:///...``, ``postgresql://user@host:port/db``).
        study_name: name shared by every worker of the study.
        seed: sampler seed (TPE); worker ``w`` uses ``seed * 1000 + w``.
        worker: index of this worker (gives each worker of a shared study its own sampler stream).
        pruner_startup_trials: trials finished before the median pruner may prune.
        pruner_warmup_steps: first step at which a trial may be pruned.
        heartbeat_interval: seconds between heartbeats of a running trial.
        grace_period: seconds without heartbeat after which a running trial counts as dead
            (``None``: twice the interval).
        max_retry: re-runs of a trial whose worker died.
        enqueue_presets: the study's creator enqueues the ``sss3dgs`` and ``diamond`` presets first.
    """

    storage: str
    study_name: str = "diamond-sss"
    seed: int = 0
    worker: int = 0
    pruner_startup_trials: int = 3
    pruner_warmup_steps: int = 0
    heartbeat_interval: int = 60
    grace_period: int | None = None
    max_retry: int = 2
    enqueue_presets: bool = True

    def __post_init__(self) -> None:
        if self.heartbeat_interval <= 0:
            raise ValueError(f"heartbeat_interval must be positive, got {self.heartbeat_interval}")
        if self.worker < 0:
            raise ValueError(f"worker must be >= 0, got {self.worker}")


def default_storage(out: Path) -> str:
    """``sqlite:///<out>/study.db`` (the folder is created)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{(out / 'study.db').resolve()}"


def _retry_callback(max_retry: int) -> tuple[str, Callable[[optuna.Study, FrozenTrial], None]]:
    """The storage keyword and callback that re-queue a dead worker's trial (Optuna 4.x and 5.x names)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        warnings.simplefilter("ignore", FutureWarning)
        if hasattr(optuna.storages, "RetryHeartbeatStaleTrialCallback"):
            callback = optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry)
            return "heartbeat_stale_trial_callback", callback
        return "failed_trial_callback", optuna.storages.RetryFailedTrialCallback(max_retry)


def masked_url(url: str) -> str:
    """``url`` with its password replaced by ``***`` (for messages and reports)."""
    return sqlalchemy.engine.make_url(url).render_as_string(hide_password=True)


def with_installed_driver(url: str) -> str:
    """``postgresql://`` URLs name the ``psycopg2`` driver when it is the one installed.

    (SQLAlchemy 2.1 defaults to ``psycopg`` 3; the ``tune`` extra installs ``psycopg2``.)
    """
    try:
        parsed = sqlalchemy.engine.make_url(url)
    except sqlalchemy.exc.ArgumentError:
        return url
    missing_default = find_spec("psycopg") is None
    if parsed.drivername == "postgresql" and missing_default and find_spec("psycopg2") is not None:
        return parsed.set(drivername="postgresql+psycopg2").render_as_string(hide_password=False)
    return url


def make_storage(settings: StudySettings) -> optuna.storages.RDBStorage:
    """An RDB storage with heartbeats and the retry callback; SQLite waits on locks instead of failing.

    Creating Optuna's tables is retried: workers started together on an empty database race to do it.
    """
    url = with_installed_driver(settings.storage)
    engine_kwargs: dict[str, Any] = {"pool_pre_ping": True}
    if url.startswith("sqlite"):
        engine_kwargs = {"connect_args": {"timeout": 60}}
    keyword, callback = _retry_callback(settings.max_retry)
    grace = settings.grace_period if settings.grace_period is not None else 2 * settings.heartbeat_interval
    attempt = 0
    while True:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                return optuna.storages.RDBStorage(url, engine_kwargs=engine_kwargs,
                                                  heartbeat_interval=settings.heartbeat_interval,
                                                  grace_period=grace, **{keyword: callback})
        except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError):
            attempt += 1
            if attempt == SCHEMA_ATTEMPTS:
                raise
            time.sleep(0.5 * attempt)
        except sqlalchemy.exc.ArgumentError as exc:
            raise ValueError(f"storage '{url}' is not an SQLAlchemy URL ({exc})") from exc
        except sqlalchemy.exc.OperationalError as exc:
            raise ValueError(f"cannot open storage {masked_url(url)}: {exc.orig}") from exc
        except ImportError as exc:
            raise ValueError(f"storage {masked_url(url)}: its database driver is not installed "
                             "(pip install 'diamond-sss[tune]' for PostgreSQL)") from exc


def open_study(settings: StudySettings, fingerprint: dict[str, Any], *, create: bool = True) -> optuna.Study:
    """Create the study (enqueueing the presets) or join it; a study made with other settings is refused.

    ``fingerprint`` is what every worker must agree on (trial length, regime, validation split, ...).
    ``create=False`` (``tune --report-only``) opens an existing study only: a name that is not in the storage is an
    error listing the studies there, and no study is created.
    """
    storage = make_storage(settings)
    sampler = optuna.samplers.TPESampler(seed=settings.seed * 1000 + settings.worker, constant_liar=True)
    pruner = optuna.pruners.MedianPruner(n_startup_trials=settings.pruner_startup_trials,
                                         n_warmup_steps=settings.pruner_warmup_steps)
    if not create:
        return _join_study(storage, settings, sampler, pruner, fingerprint)
    try:
        study = optuna.create_study(storage=storage, study_name=settings.study_name, direction="maximize",
                                    sampler=sampler, pruner=pruner)
    except optuna.exceptions.DuplicatedStudyError:
        return _join_study(storage, settings, sampler, pruner, fingerprint)
    if settings.enqueue_presets:
        for preset in (ORIGINAL_PRESET, BEST_PRESET):
            study.enqueue_trial(preset_params(preset), user_attrs={"preset": preset})
    study.set_user_attr("settings", fingerprint)
    return study


def _join_study(storage: optuna.storages.RDBStorage, settings: StudySettings, sampler: optuna.samplers.BaseSampler,
                pruner: optuna.pruners.BasePruner, fingerprint: dict[str, Any]) -> optuna.Study:
    """The existing study ``settings.study_name``, refused when made with settings other than ``fingerprint``."""
    try:
        study = optuna.load_study(study_name=settings.study_name, storage=storage, sampler=sampler, pruner=pruner)
    except KeyError:
        present = optuna.get_all_study_names(storage)
        raise ValueError(f"study '{settings.study_name}' not found in {masked_url(settings.storage)}; studies there: "
                         f"{present or 'none'} (check --study and --storage)") from None
    recorded = _wait_for_fingerprint(study)
    if recorded != fingerprint:
        changed = sorted(k for k in {*recorded, *fingerprint} if recorded.get(k) != fingerprint.get(k))
        raise ValueError(f"study '{settings.study_name}' was created with other settings "
                         f"({', '.join(changed)}); use the same options or another --study name")
    return study


def _wait_for_fingerprint(study: optuna.Study, timeout: float = 60.0) -> dict[str, Any]:
    """The creator's settings (it writes them just after creating the study)."""
    deadline = time.monotonic() + timeout
    while "settings" not in study.user_attrs:
        if time.monotonic() > deadline:
            raise ValueError(f"study '{study.study_name}' has no recorded settings: "
                             "was it made by diamond-sss tune?")
        time.sleep(0.2)
    return study.user_attrs["settings"]


def budget_used(trials: list[FrozenTrial]) -> int:
    """Trials that count against the budget: finished, running, queued, or failed by divergence.

    A trial failed because its worker died does not count: its re-queued copy does.
    """
    return sum(t.state in FINISHED_OR_ACTIVE or (t.state == TrialState.FAIL and "failure" in t.user_attrs)
               for t in trials)


def run_worker(study: optuna.Study, objective: Callable[[optuna.Trial], float], n_trials: int, *,
               timeout: float | None = None, poll_seconds: float = 1.0) -> list[int]:
    """Run trials until the study holds ``n_trials`` (shared by all workers); returns the numbers run here.

    Queued trials (presets, re-queued trials of dead workers) run first. When the budget is spent but
    other workers' trials still run, the worker polls every ``poll_seconds`` until they end (re-running
    any whose worker died), so the study is complete when the last worker exits. Two workers starting
    their last trials at the same instant may overshoot the budget by one; no trial is ever run twice.
    """
    if n_trials < 0:
        raise ValueError(f"trials must be >= 0, got {n_trials}")
    started = time.monotonic()
    ran: list[int] = []

    def record(_: optuna.Study, trial: FrozenTrial) -> None:
        ran.append(trial.number)

    while timeout is None or time.monotonic() - started < timeout:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            optuna.storages.fail_stale_trials(study)
        trials = study.get_trials(deepcopy=False)
        waiting = any(t.state == TrialState.WAITING for t in trials)
        if waiting or budget_used(trials) < n_trials:
            study.optimize(objective, n_trials=1, catch=(FloatingPointError,), callbacks=[record],
                           gc_after_trial=True)
        elif any(t.state == TrialState.RUNNING for t in trials):
            time.sleep(poll_seconds)
        else:
            break
    return ran
