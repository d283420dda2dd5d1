"""Parsing of ``transforms_<split>.json`` files (method.md §1), both variants, into per-image records.

* SSS-3DGS variant: one frame per camera view with ``transform_matrix``, ``file_paths`` (one image per
  light), ``light_positions`` and optional ``light_intensities`` (and ``mask_paths``).
* Per-image variant (NRHints / GS3 / SSD-GS): one frame per image with ``file_path``, ``transform_matrix``,
  ``pl_pos`` and optional ``pl_intensity`` (and ``mask_path``).

Intrinsics come from ``camera_angle_x`` (+ optional ``camera_angle_y``) or ``fl_x, fl_y, cx, cy``, at the
top level or per frame (per frame wins), in pixels of ``w``/``width`` x ``h``/``height`` (default: the image
file's size; the dataset scales them to the file's size). Images named in the object's ``exclude_list.txt``
are skipped (the SSS-3DGS release's reader does the same). Optional
per-view geometry maps: ``depth_path`` (float32 ``.npy`` camera z) and ``normal_path`` (float32 ``.npy``
world-space unit normals). Nothing is written here and no pixel is decoded.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from diamond_sss.data.images import read_header
from diamond_sss.errors import DataError, data_error

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels of the full-resolution image; ``fov_x`` set when given as an angle."""

    fx: float | None
    fy: float | None
    cx: float | None
    cy: float | None
    fov_x: float | None = None
    fov_y: float | None = None


@dataclass(frozen=True)
class ImageRecord:
    """One (view, light) image as written in the JSON, before deduplication into the lattice."""

    frame: int
    c2w: np.ndarray
    intrinsics: Intrinsics
    width: int
    height: int
    image_path: Path
    mask_path: Path | None
    light_position: np.ndarray
    light_intensity: np.ndarray
    depth_path: Path | None
    normal_path: Path | None
    file_size: tuple[int, int]


def transforms_path(root: Path, split: str) -> Path:
    """``root/transforms_<split>.json``; a clear error listing the splits present when it is missing."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"data folder not found: {root}")
    path = root / f"transforms_{split}.json"
    if not path.is_file():
        raise DataError(f"{path}: split '{split}' not found; splits in {root}: {available_splits(root) or 'none'}")
    return path


def available_splits(root: Path) -> list[str]:
    """Names of the splits (``transforms_<name>.json``) in a data folder."""
    return sorted(p.stem[len("transforms_"):] for p in Path(root).glob("transforms_*.json"))


@dataclass(frozen=True)
class DeclaredCamera:
    """A lattice camera listed under the top-level ``cameras`` key (it may have no image in this file)."""

    index: int
    c2w: np.ndarray
    intrinsics: Intrinsics
    width: int | None
    height: int | None


@dataclass(frozen=True)
class DeclaredLight:
    """A lattice light listed under the top-level ``lights`` key (it may have no image in this file)."""

    index: int
    position: np.ndarray
    intensity: np.ndarray


@dataclass(frozen=True)
class ParsedTransforms:
    """Every image of a transforms file, plus the lattice cameras and lights it declares up front, and the
    image entries skipped because the object's ``exclude_list.txt`` names them."""

    records: list[ImageRecord]
    cameras: list[DeclaredCamera]
    lights: list[DeclaredLight]
    excluded: tuple[str, ...] = ()
    premultiplied_alpha: bool | None = None


EXCLUDE_LIST = "exclude_list.txt"


def read_exclude_list(root: Path) -> frozenset[str]:
    """Image names of ``root/exclude_list.txt`` (one a line, with or without ``.png``; ``#`` comments).

    The SSS-3DGS release lists there the images of an object its reader skips; no file: nothing skipped.
    """
    path = Path(root) / EXCLUDE_LIST
    if not path.is_file():
        return frozenset()
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise data_error(path, f"not a UTF-8 text file ({exc})") from exc
    return frozenset(_image_name(line) for line in lines if line.strip() and not line.lstrip().startswith("#"))


def _image_name(entry: str) -> str:
    """``entry`` without surrounding spaces, a leading ``./`` and a ``.png`` suffix (``/`` separators)."""
    name = entry.strip().replace("\\", "/")
    name = name.removeprefix("./")
    return name[:-4] if name.lower().endswith(".png") else name


def is_excluded(entry: str, excluded: frozenset[str]) -> bool:
    """Whether the image ``entry`` (a ``file_path(s)`` value) is named in the exclude list, as a relative
    path or by its file name."""
    name = _image_name(entry)
    return name in excluded or name.rsplit("/", 1)[-1] in excluded


def parse_transforms(path: Path) -> ParsedTransforms:
    """Read a transforms JSON file into one :class:`ImageRecord` per image (both variants).

    Optional top-level ``premultiplied_alpha`` (bool: how the RGBA files store colour, ``data/conventions.py``),
    ``cameras`` (``[{"transform_matrix": ..., "fl_x"/...: ...}]``) and ``lights``
    (``[{"position": [x,y,z], "intensity": [r,g,b]}]``) declare the capture's full lattice, including cameras
    and lights with no image in this file (e.g. generated data, or the novel views of a regime); they take
    the first lattice indices, in order.
    """
    meta = _read_object(path)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise data_error(path, "expected a non-empty list", key="frames")
    root = path.parent
    excluded = read_exclude_list(root)
    records: list[ImageRecord] = []
    skipped: list[str] = []
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise data_error(path, "expected a JSON object", frame=index)
        records.extend(_parse_frame(path, root, meta, frame, index, excluded, skipped))
    if not records:
        raise data_error(path, f"every image is named in {root / EXCLUDE_LIST}", key="frames")
    premultiplied = meta.get("premultiplied_alpha")
    if premultiplied is not None and not isinstance(premultiplied, bool):
        raise data_error(path, f"expected true or false, got {premultiplied!r}", key="premultiplied_alpha")
    return ParsedTransforms(records, _declared_cameras(path, meta), _declared_lights(path, meta), tuple(skipped),
                            premultiplied)


def _read_object(path: Path) -> dict:
    """The JSON object in ``path``; a :class:`DataError` naming the file when it is not one."""
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise data_error(path, f"invalid JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise data_error(path, "expected a JSON object at the top level")
    return meta


def parse_rig(path: Path) -> tuple[list[DeclaredCamera], list[DeclaredLight]]:
    """A light stage's layout without images: the top-level ``cameras`` and ``lights`` of a transforms file (as in
    :func:`parse_transforms`; ``frames``, if any, are not read). Each must be a non-empty list."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such rig file (a transforms file with top-level 'cameras' and 'lights')")
    meta = _read_object(path)
    for key in ("cameras", "lights"):
        if not isinstance(meta.get(key), list) or not meta[key]:
            raise data_error(path, "a rig file needs a non-empty list of the light stage's " + key, key=key)
    return _declared_cameras(path, meta), _declared_lights(path, meta)


def _declared_cameras(path: Path, meta: dict) -> list[DeclaredCamera]:
    entries = meta.get("cameras", [])
    if not isinstance(entries, list):
        raise data_error(path, "expected a list of camera objects", key="cameras")
    cameras = []
    for index, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise data_error(path, f"cameras[{index}]: expected a JSON object", key="cameras")
        try:
            c2w = _matrix(path, entry, index)
            intrinsics = _intrinsics(path, meta, entry, index)
        except DataError as exc:
            raise DataError(str(exc).replace(f"frame {index}", f"cameras[{index}]")) from exc
        width = _size(path, meta, entry, index, ("w", "width"), 0)
        height = _size(path, meta, entry, index, ("h", "height"), 0)
        cameras.append(DeclaredCamera(index, c2w, intrinsics, width or None, height or None))
    return cameras


def _declared_lights(path: Path, meta: dict) -> list[DeclaredLight]:
    entries = meta.get("lights", [])
    if not isinstance(entries, list):
        raise data_error(path, "expected a list of light objects", key="lights")
    lights = []
    for index, entry in enumerate(entries):
        if not isinstance(entry, dict) or "position" not in entry:
            raise data_error(path, f"lights[{index}]: expected an object with 'position'", key="lights")
        lights.append(DeclaredLight(index, _vector(path, entry["position"], index, f"lights[{index}].position"),
                                    _intensity(path, entry.get("intensity", 1.0), index,
                                               f"lights[{index}].intensity")))
    return lights


def _parse_frame(path: Path, root: Path, meta: dict, frame: dict, index: int, excluded: frozenset[str],
                 skipped: list[str]) -> list[ImageRecord]:
    c2w = _matrix(path, frame, index)
    intrinsics = _intrinsics(path, meta, frame, index)
    depth_path = _optional_file(path, root, frame, index, "depth_path")
    normal_path = _optional_file(path, root, frame, index, "normal_path")
    if "file_paths" in frame:
        files = _list(path, frame, index, "file_paths")
        positions = _list(path, frame, index, "light_positions")
        if len(positions) != len(files):
            raise data_error(path, f"has {len(positions)} entries but 'file_paths' has {len(files)}",
                             frame=index, key="light_positions")
        intensities = frame.get("light_intensities", [[1.0, 1.0, 1.0]] * len(files))
        if not isinstance(intensities, list) or len(intensities) != len(files):
            raise data_error(path, f"expected a list of {len(files)} [r,g,b] entries", frame=index,
                             key="light_intensities")
        masks = frame.get("mask_paths", [None] * len(files))
        if not isinstance(masks, list) or len(masks) != len(files):
            raise data_error(path, f"expected a list of {len(files)} paths", frame=index, key="mask_paths")
        items = [
            (files[k], masks[k], _vector(path, positions[k], index, f"light_positions[{k}]"),
             _intensity(path, intensities[k], index, f"light_intensities[{k}]"))
            for k in range(len(files))
        ]
    elif "file_path" in frame:
        if "pl_pos" not in frame:
            raise data_error(path, "missing (the light position of this image)", frame=index, key="pl_pos")
        items = [(frame["file_path"], frame.get("mask_path"), _vector(path, frame["pl_pos"], index, "pl_pos"),
                  _intensity(path, frame.get("pl_intensity", 1.0), index, "pl_intensity"))]
    else:
        raise data_error(path, "missing: expected 'file_paths' (SSS-3DGS) or 'file_path' (per-image)",
                         frame=index, key="file_paths")
    records = []
    for k, (file_entry, mask_entry, light_pos, light_rgb) in enumerate(items):
        key = "file_path" if "file_path" in frame else f"file_paths[{k}]"
        if isinstance(file_entry, str) and is_excluded(file_entry, excluded):
            skipped.append(file_entry)
            continue
        image_path = _resolve_image(path, root, file_entry, index, key)
        header = read_header(image_path)
        width = _size(path, meta, frame, index, ("w", "width"), header.width)
        height = _size(path, meta, frame, index, ("h", "height"), header.height)
        mask_path = _resolve_mask(path, root, image_path, mask_entry, index, key, header.channels)
        records.append(ImageRecord(
            frame=index, c2w=c2w, intrinsics=intrinsics, width=width, height=height, image_path=image_path,
            mask_path=mask_path, light_position=light_pos, light_intensity=light_rgb, depth_path=depth_path,
            normal_path=normal_path, file_size=(header.width, header.height),
        ))
    return records


def _list(path: Path, frame: dict, index: int, key: str) -> list:
    if key not in frame:
        raise data_error(path, "missing", frame=index, key=key)
    value = frame[key]
    if not isinstance(value, list) or not value:
        raise data_error(path, f"expected a non-empty list, got {type(value).__name__}", frame=index, key=key)
    return value


def _matrix(path: Path, frame: dict, index: int) -> np.ndarray:
    if "transform_matrix" not in frame:
        raise data_error(path, "missing", frame=index, key="transform_matrix")
    try:
        matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise data_error(path, f"not a numeric matrix ({exc})", frame=index, key="transform_matrix") from exc
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4):
        raise data_error(path, f"expected 4x4, got shape {list(matrix.shape)}", frame=index, key="transform_matrix")
    if not np.isfinite(matrix).all():
        raise data_error(path, "contains NaN or infinity", frame=index, key="transform_matrix")
    det = np.linalg.det(matrix[:3, :3])
    if abs(det) < 1e-8 or not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise data_error(path, f"not an invertible rigid transform (det of rotation {det:.3g}, last row "
                         f"{matrix[3].tolist()})", frame=index, key="transform_matrix")
    return matrix


def _vector(path: Path, value: Any, index: int, key: str) -> np.ndarray:
    try:
        vector = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise data_error(path, f"not numeric ({exc})", frame=index, key=key) from exc
    if vector.shape != (3,) or not np.isfinite(vector).all():
        raise data_error(path, f"expected 3 finite numbers, got {value!r}", frame=index, key=key)
    return vector


def _intensity(path: Path, value: Any, index: int, key: str) -> np.ndarray:
    if isinstance(value, (int, float)):
        value = [value] * 3
    vector = _vector(path, value, index, key)
    if (vector < 0).any():
        raise data_error(path, f"light intensity must be non-negative, got {value!r}", frame=index, key=key)
    return vector


def _number(path: Path, source: dict, key: str, index: int | None) -> float | None:
    if key not in source:
        return None
    value = source[key]
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise data_error(path, f"expected a finite number, got {value!r}", frame=index, key=key)
    return float(value)


def _intrinsics(path: Path, meta: dict, frame: dict, index: int) -> Intrinsics:
    def pick(key: str) -> float | None:
        local = _number(path, frame, key, index)
        return local if local is not None else _number(path, meta, key, None)

    fx, fy, cx, cy = pick("fl_x"), pick("fl_y"), pick("cx"), pick("cy")
    fov_x, fov_y = pick("camera_angle_x"), pick("camera_angle_y")
    if fx is None and fov_x is None:
        raise data_error(path, "missing: need 'camera_angle_x' or 'fl_x' (top level or per frame)",
                         frame=index, key="camera_angle_x")
    for key, value in (("fl_x", fx), ("fl_y", fy), ("camera_angle_x", fov_x), ("camera_angle_y", fov_y)):
        if value is not None and value <= 0:
            raise data_error(path, f"must be positive, got {value}", frame=index, key=key)
    return Intrinsics(fx=fx, fy=fy if fy is not None else fx, cx=cx, cy=cy, fov_x=fov_x, fov_y=fov_y)


def _size(path: Path, meta: dict, frame: dict, index: int, keys: tuple[str, str], default: int) -> int:
    """Image side in pixels the intrinsics are stated for: ``w``/``width`` (``h``/``height``) of the frame,
    else of the top level, else the image file's."""
    for source, where in ((frame, index), (meta, None)):
        for key in keys:
            if key in source:
                value = source[key]
                if isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0 or value % 1:
                    raise data_error(path, f"expected a positive whole number of pixels, got {value!r}",
                                     frame=where, key=key)
                return int(value)
    return default


def _resolve_image(path: Path, root: Path, entry: Any, index: int, key: str) -> Path:
    if not isinstance(entry, str) or not entry:
        raise data_error(path, f"expected a relative file path, got {entry!r}", frame=index, key=key)
    base = (root / entry).resolve()
    candidates = [base] + [base.with_name(base.name + suffix) for suffix in IMAGE_SUFFIXES]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise data_error(path, f"image file not found: {base} (also tried the suffixes {list(IMAGE_SUFFIXES)})",
                     frame=index, key=key)


def _resolve_mask(path: Path, root: Path, image_path: Path, entry: Any, index: int, key: str,
                  channels: int) -> Path | None:
    if entry is not None:
        mask = (root / str(entry)).resolve()
        if not mask.is_file():
            raise data_error(path, f"mask file not found: {mask}", frame=index, key="mask_path")
        return mask
    if channels in (2, 4):
        return None
    for candidate in (image_path.with_name(image_path.stem + "_mask.png"),
                      image_path.parent / "masks" / (image_path.stem + ".png")):
        if candidate.is_file():
            return candidate
    raise data_error(path, f"{image_path} has no alpha channel and no mask file (give 'mask_path' / 'mask_paths', "
                     f"or put {image_path.stem}_mask.png beside it)", frame=index, key=key)


def _optional_file(path: Path, root: Path, frame: dict, index: int, key: str) -> Path | None:
    if key not in frame:
        return None
    entry = frame[key]
    if not isinstance(entry, str):
        raise data_error(path, f"expected a relative path, got {entry!r}", frame=index, key=key)
    file = (root / entry).resolve()
    if not file.is_file():
        raise data_error(path, f"file not found: {file}", frame=index, key=key)
    return file
