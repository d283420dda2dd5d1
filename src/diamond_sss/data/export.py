"""Export a capture regime's images as a capture of their own: the sparse capture a user would bring.

``export_regime`` writes ``transforms_<split>.json`` listing only the images the regime selects (their frames,
cameras, lights and every other key unchanged, the unselected images and the frames left without one dropped), and
copies those images, their masks and the kept frames' depth / normal maps to the same relative paths. The test
split is copied whole so the export can be evaluated. The export is built in a temporary folder beside ``out`` and
renamed into place: ``out`` is either absent or complete.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.regimes import RegimeSelection, select_regime
from diamond_sss.data.transforms import is_excluded, parse_transforms, read_exclude_list, transforms_path
from diamond_sss.errors import DataError, data_error
from diamond_sss.utils.io import atomic_write_json, default_mode

_PER_IMAGE_LISTS = ("file_paths", "light_positions", "light_intensities", "mask_paths")
EVALUATION_SPLIT = "test"
RECORD_NAME = "subset.json"


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_regime` wrote: the folder, the selection, images per split, and a note on a missing
    evaluation split (``None`` when there is nothing to say)."""

    out: Path
    selection: RegimeSelection
    images: dict[str, int]
    note: str | None


def filter_transforms(json_path: Path, keep: Callable[[Path], bool]) -> tuple[dict, list[Path], int]:
    """The transforms payload of ``json_path`` restricted to the images ``keep(resolved_image_path)`` accepts, the
    files those images need (image, mask, their frame's depth and normal maps) and the number of images kept.

    Images named in the object's ``exclude_list.txt`` are dropped, as the reader skips them."""
    payload = json.loads(json_path.read_text())
    root = json_path.parent
    excluded = read_exclude_list(root)
    records_of_frame = defaultdict(list)
    for record in parse_transforms(json_path).records:
        records_of_frame[record.frame].append(record)
    frames, files, kept_images = [], [], 0
    for index, frame in enumerate(payload["frames"]):
        records = iter(records_of_frame[index])
        entries = frame["file_paths"] if "file_paths" in frame else [frame["file_path"]]
        kept = []
        for k, entry in enumerate(entries):
            if isinstance(entry, str) and is_excluded(entry, excluded):
                continue
            record = next(records)
            if keep(record.image_path):
                kept.append(k)
                files += [path for path in (record.image_path, record.mask_path) if path is not None]
        if not kept:
            continue
        maps = records_of_frame[index][0]
        files += [path for path in (maps.depth_path, maps.normal_path) if path is not None]
        if "file_paths" in frame:
            frame = {**frame, **{key: [frame[key][k] for k in kept] for key in _PER_IMAGE_LISTS if key in frame}}
        frames.append(frame)
        kept_images += len(kept)
    return {**payload, "frames": frames}, list(dict.fromkeys(files)), kept_images


def export_regime(data: Path, out: Path, regime: str, split: str = "train", seed: int = 0) -> ExportResult:
    """Write into ``out`` a capture holding only the images regime ``regime`` (seed ``seed``) selects from ``split``
    of ``data``, plus the whole test split (see the module docstring).

    Errors (``out`` exists, a bad regime, a file outside ``data``) are raised before anything is written."""
    data, out = Path(data), Path(out)
    if out.exists():
        raise DataError(f"{out} exists; the export writes a new folder (remove it or name another)")
    dataset = OLATDataset(data, split)
    selection = select_regime(dataset, regime, seed)
    chosen = {dataset.observations[i].image_path for i in selection.observations}
    plans = {split: filter_transforms(dataset.json_path, chosen.__contains__)}
    note = None
    if split != EVALUATION_SPLIT:
        if (data / f"transforms_{EVALUATION_SPLIT}.json").is_file():
            plans[EVALUATION_SPLIT] = filter_transforms(transforms_path(data, EVALUATION_SPLIT), lambda _: True)
        else:
            note = f"{data} has no transforms_{EVALUATION_SPLIT}.json: the export has no {EVALUATION_SPLIT} split"
    root = dataset.root
    copies = {}
    for name, (_, files, _) in plans.items():
        for file in files:
            if not file.is_relative_to(root):
                raise data_error(data / f"transforms_{name}.json", f"{file} lies outside {root}; the export keeps "
                                 "the paths relative to the data folder")
            copies[file] = file.relative_to(root)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        for source, rel in copies.items():
            (staging / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, staging / rel)
        for name, (payload, _, _) in plans.items():
            atomic_write_json(staging / f"transforms_{name}.json", payload)
        images = {name: count for name, (_, _, count) in plans.items()}
        atomic_write_json(staging / RECORD_NAME, {"source": str(root), "split": split, "regime": regime, "seed": seed,
                                                  "images": images, "selection": selection.to_json()})
        os.chmod(staging, default_mode(directory=True))
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return ExportResult(out=out, selection=selection, images=images, note=note)
