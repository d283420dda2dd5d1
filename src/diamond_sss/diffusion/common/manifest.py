"""Generated images on disk, one layout for both diffusion models.

``<out>/images/<name>.png`` (sRGB, premultiplied colour, alpha = mask), ``<out>/masks/<name>.png`` (8-bit mask)
and ``<out>/manifest.json``, a list of ``{view, light, image, mask}`` with paths relative to ``<out>``; ``view`` is
the lattice view index, or ``null`` for a novel view made at a camera given by its pose (off the lattice). Older
novel-view folders (``<name>.png`` and ``<name>_mask.png`` beside the manifest) read the same: the paths are
taken from the manifest.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from diamond_sss.utils.io import atomic_write_json

MANIFEST_NAME = "manifest.json"
_FIELDS = {"view": (int, type(None)), "light": int, "image": str, "mask": str}


@dataclass(frozen=True)
class GeneratedImage:
    """One generated image: view (``None`` off the lattice: a camera given by its pose) and light indices, the
    image (RGBA or RGB) and an optional mask."""

    view: int | None
    light: int
    image: Path
    mask: Path | None = None


def image_paths(out: str | os.PathLike, name: str) -> tuple[Path, Path]:
    """Where the image ``name`` and its mask go in ``out``."""
    return Path(out) / "images" / f"{name}.png", Path(out) / "masks" / f"{name}.png"


def write_image_manifest(out: str | os.PathLike, items: Sequence[GeneratedImage]) -> Path:
    """Write ``out/manifest.json`` listing ``items`` (files inside ``out``, each with a mask); returns its path."""
    out = Path(out)
    entries = []
    for item in items:
        if item.mask is None:
            raise ValueError(f"{item.image}: a generated image needs a mask file")
        entries.append({"view": item.view, "light": item.light, "image": item.image.relative_to(out).as_posix(),
                        "mask": item.mask.relative_to(out).as_posix()})
    return atomic_write_json(out / MANIFEST_NAME, entries)


def read_image_manifest(path: str | os.PathLike) -> list[GeneratedImage]:
    """The images listed in ``path``, their files resolved against its folder."""
    path = Path(path)
    try:
        entries = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON ({error})") from error
    if not isinstance(entries, list):
        raise ValueError(f"{path} must hold a list of {{view, light, image, mask}} entries")  # noqa: TRY004
    items = []
    for index, entry in enumerate(entries):
        fields = entry if isinstance(entry, dict) else {}
        bad = [key for key, kind in _FIELDS.items()
               if key not in fields or not isinstance(fields[key], kind) or isinstance(fields[key], bool)]
        if bad:
            raise ValueError(f"{path}, entry {index}: expected an integer (or null) view, an integer light and "
                             "image and mask paths; "
                             f"bad or missing {bad} in {entry!r}")
        items.append(GeneratedImage(entry["view"], entry["light"], path.parent / entry["image"],
                                    path.parent / entry["mask"]))
    return items
