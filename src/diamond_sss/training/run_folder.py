"""Whether a run folder may be resumed or reused with a configuration: the settings it records against the given
ones, and its finished summary (its scene is read by :func:`diamond_sss.runs.folder.load_scene`).

Only the configuration is imported here, not the training loop.
"""

from __future__ import annotations

from pathlib import Path

from diamond_sss.errors import DataError
from diamond_sss.training.config import TrainConfig
from diamond_sss.training.overrides import load_run_config
from diamond_sss.utils.io import move_aside, read_json, sha256_json

RESUMABLE_KEYS = frozenset({"iterations", "log_every", "checkpoint_every", "keep_checkpoints", "image_log_every",
                            "device", "cpu_threads"})
"""Settings a resumed run may change: its length, logging and where it runs; any other change would continue a
model with settings it was not trained with (or fail to load it, e.g. another MLP width)."""


def changed_settings(run_dir: Path, cfg: TrainConfig) -> dict[str, tuple]:
    """``flat key -> (recorded, given)`` for the settings of ``cfg`` that differ from those the run folder
    records (empty when it records none), :data:`RESUMABLE_KEYS` aside."""
    if not (Path(run_dir) / "config.json").is_file():
        return {}
    recorded, given = load_run_config(run_dir).flat(), cfg.flat()
    return {key: (recorded[key], value) for key, value in given.items()
            if key not in RESUMABLE_KEYS and recorded.get(key) != value}


def move_aside_if_trained_otherwise(run_dir: Path, cfg: TrainConfig) -> Path | None:
    """Rename a run folder that records other settings than ``cfg`` (:func:`changed_settings`) to
    ``<run_dir>.<first 8 hex of the changed keys' hash>`` and return the new path, so that a job that reuses finished
    runs trains this one again instead of reporting a model made with other settings; ``None`` when nothing changed
    (or there is no run). Nothing is deleted."""
    changed = changed_settings(run_dir, cfg)
    return move_aside(Path(run_dir), sha256_json(sorted(changed))[:8]) if changed else None


def check_resumable(run_dir: Path, cfg: TrainConfig) -> None:
    """Refuse to resume ``run_dir`` with other settings than it was trained with, naming them."""
    changed = changed_settings(run_dir, cfg)
    if changed:
        listed = ", ".join(f"{key}: {old!r} -> {new!r}" for key, (old, new) in sorted(changed.items()))
        raise ValueError(f"{run_dir} was trained with other settings ({listed}); resume it with the same settings "
                         "or train into another --out")


def check_same_images(run_dir: Path, data: Path, regime: str, content_sha256: str) -> None:
    """Refuse to resume ``run_dir`` on other images than those it records in ``data.json`` (the digest of the images it
    trained on; for runs without one, the capture folder and regime), naming both: a finished run would otherwise be
    reported as the model of images it never saw."""
    path = Path(run_dir) / "data.json"
    if not path.is_file():
        return
    recorded = read_json(path)
    if not isinstance(recorded, dict):
        raise DataError(f"{path}: expected a JSON object with the keys data, regime and content_sha256")
    same = (recorded.get("content_sha256") == content_sha256 if recorded.get("content_sha256")
            else (recorded.get("data"), recorded.get("regime")) == (str(Path(data).resolve()), regime))
    if not same:
        raise ValueError(f"{run_dir} was trained on other images ({recorded.get('data')}, regime "
                         f"{recorded.get('regime')!r}) than {Path(data).resolve()} with regime {regime!r}; resume it "
                         "with the same images or train into another --out")


def finished_summary(run_dir: Path, iterations: int) -> dict | None:
    """What a run recorded (``train_summary.json``) when it finished ``iterations`` steps and wrote its model;
    ``None`` otherwise (resuming it then continues from its newest checkpoint)."""
    summary_path, model_path = Path(run_dir) / "train_summary.json", Path(run_dir) / "model.safetensors"
    if not (summary_path.is_file() and model_path.is_file()):
        return None
    summary = read_json(summary_path)
    return summary if summary.get("steps") == iterations else None
