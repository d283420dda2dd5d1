"""Writing generated images as a capture on the real capture's lattice (a ``transforms_<name>.json``).

The file declares every camera and light of the real lattice up front (top-level ``cameras`` / ``lights``),
so its view and light indices are the real capture's, and lists the generated images per view (SSS-3DGS
variant) with paths relative to the file's folder and a mask file for each image. It declares
``premultiplied_alpha: true``: generated images are written premultiplied (``diffusion/common/manifest.py``).
A view's camera is declared at the size of its images (a diffusion model's resolution, intrinsics scaled to it), so
they are read at the size they were made at; a view without images keeps the lattice's size.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from diamond_sss.data.conventions import opencv_w2c_to_opengl_c2w, scale_intrinsics
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.images import read_header
from diamond_sss.diffusion.common.manifest import GeneratedImage
from diamond_sss.utils.io import atomic_write_json


def lattice_header(lattice: OLATDataset, sizes: dict[int, tuple[int, int]] | None = None) -> dict:
    """The top-level ``cameras`` / ``lights`` entries that reproduce ``lattice``'s indices; view ``v`` of ``sizes``
    declared at ``sizes[v] = (w, h)`` (intrinsics scaled by ``w / width``, ``h / height``), the others at their size."""
    cameras = []
    for view, camera in enumerate(lattice.cameras):
        c2w = opencv_w2c_to_opengl_c2w(camera.w2c.double())
        width, height = (sizes or {}).get(view, (camera.width, camera.height))
        K = camera.K if (width, height) == (camera.width, camera.height) else scale_intrinsics(
            camera.K.double(), width / camera.width, height / camera.height)
        cameras.append({"transform_matrix": c2w.tolist(), "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
                        "cx": float(K[0, 2]), "cy": float(K[1, 2]), "w": width, "h": height})
    lights = [{"position": light.position.tolist(), "intensity": light.intensity.tolist()}
              for light in lattice.lights]
    return {"cameras": cameras, "lights": lights}


def check_on_lattice(items: list[GeneratedImage], lattice: OLATDataset) -> list[GeneratedImage]:
    """``items`` as they are when every view and light index is one of ``lattice``'s; else a ``ValueError`` naming
    the first image outside it (a novel view made at a camera given by its pose, view ``None``, or a hand-edited
    manifest)."""
    for item in items:
        if item.view is None:
            raise ValueError(f"{item.image}: a novel view at a camera given by its pose (view null in its manifest), "
                             "not one of the lattice's views: only lattice views join a capture")
        if not (0 <= item.view < len(lattice.cameras) and 0 <= item.light < len(lattice.lights)):
            raise ValueError(f"{item.image}: view {item.view} / light {item.light} outside the lattice's "
                             f"{len(lattice.cameras)} views x {len(lattice.lights)} lights")
    return items


def view_sizes(images: list[GeneratedImage]) -> dict[int, tuple[int, int]]:
    """The image size ``(w, h)`` of each view of ``images``, read from the files' headers; a ``ValueError`` names
    an image whose size differs from its view's first image."""
    sizes: dict[int, tuple[int, int]] = {}
    first: dict[int, GeneratedImage] = {}
    for item in images:
        header = read_header(Path(item.image))
        size = sizes.setdefault(item.view, (header.width, header.height))
        first.setdefault(item.view, item)
        if size != (header.width, header.height):
            raise ValueError(f"{item.image} is {header.width}x{header.height}, but {first[item.view].image} of the "
                             f"same view {item.view} is {size[0]}x{size[1]}: a view's images must share one size")
    return sizes


def write_capture(folder: Path, name: str, lattice: OLATDataset, images: list[GeneratedImage]) -> Path:
    """Write ``folder/transforms_<name>.json`` listing ``images`` on ``lattice``, each view's camera at the size of its
    images (:func:`view_sizes`); returns its path."""
    check_on_lattice(images, lattice)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    header = lattice_header(lattice, view_sizes(images))
    by_view: dict[int, list[GeneratedImage]] = {}
    for item in images:
        by_view.setdefault(item.view, []).append(item)
    frames = []
    for view in sorted(by_view):
        items = sorted(by_view[view], key=lambda item: item.light)
        camera = header["cameras"][view]
        frame = {key: camera[key] for key in ("transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h")}
        frame["file_paths"] = [os.path.relpath(item.image, folder) for item in items]
        frame["light_positions"] = [header["lights"][item.light]["position"] for item in items]
        frame["light_intensities"] = [header["lights"][item.light]["intensity"] for item in items]
        if all(item.mask is not None for item in items):
            frame["mask_paths"] = [os.path.relpath(item.mask, folder) for item in items]
        frames.append(frame)
    fov_x = 2.0 * math.atan(0.5 * lattice.width / float(lattice.cameras[0].K[0, 0]))
    payload = {"camera_angle_x": fov_x, "w": lattice.width, "h": lattice.height, "premultiplied_alpha": True,
               **header, "frames": frames}
    return atomic_write_json(folder / f"transforms_{name}.json", payload)
