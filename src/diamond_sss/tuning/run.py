"""The study job: open (or join) a study, run this worker's trials, write the report (``diamond-sss tune``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import optuna

from diamond_sss.tuning.objective import Objective, ObjectiveSettings
from diamond_sss.tuning.report import write_report
from diamond_sss.tuning.study import StudySettings, open_study, run_worker
from diamond_sss.tuning.validation import TuneData


@dataclass
class StudyResult:
    """The study as this worker left it, the trials it ran and the report's files."""

    study: optuna.Study
    ran: list[int]
    paths: dict[str, Path]


def run_study(data: TuneData, out: Path, objective: ObjectiveSettings, study: StudySettings, *, trials: int,
              timeout: float | None = None, report_only: bool = False) -> StudyResult:
    """One worker of a study: run trials until the study holds ``trials`` (shared by all workers) or
    ``timeout`` seconds pass, then write the report to ``out`` (``report_only``: only the report).

    Raises:
        ValueError: fewer than 2 trials with the presets enqueued, a study created with other settings, or with
            ``report_only`` a study that is not in the storage.
    """
    if study.enqueue_presets and trials < 2 and not report_only:
        raise ValueError(f"--trials {trials}: a study starts with the two preset trials; ask for at least 2 "
                         "or pass --no-enqueue-presets")
    optuna_study = open_study(study, objective.fingerprint(data), create=not report_only)
    ran = [] if report_only else run_worker(optuna_study, Objective(data, objective), trials, timeout=timeout,
                                            poll_seconds=study.heartbeat_interval / 2)
    return StudyResult(study=optuna_study, ran=ran, paths=write_report(optuna_study, out))
