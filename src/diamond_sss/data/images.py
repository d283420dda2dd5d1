"""Image files: sRGB 8/16-bit PNG <-> linear float tensors, masks, resizing.

Everything returned is linear radiance (see :mod:`diamond_sss.data.conventions`), channels last, float32.
"""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import png
import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import linear_to_srgb, pixel_grid, scale_intrinsics, srgb_to_linear
from diamond_sss.errors import DataError
from diamond_sss.utils.io import atomic_write

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class ImageHeader:
    """Size and channel count of an image file, read without decoding the pixels."""

    width: int
    height: int
    channels: int
    bit_depth: int


def read_header(path: Path) -> ImageHeader:
    """Width, height, channel count and bit depth of an image file (PNG: from the IHDR chunk)."""
    if not path.is_file():
        raise DataError(f"image file not found: {path}")
    with open(path, "rb") as handle:
        head = handle.read(33)
    if head[:8] == _PNG_SIGNATURE:
        width, height, bit_depth, color_type = struct.unpack(">IIBB", head[16:26])
        channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(color_type)
        if channels is None:
            raise DataError(f"{path}: unsupported PNG colour type {color_type}")
        if color_type == 3 and _png_palette_has_alpha(path):
            channels = 4
        return ImageHeader(width, height, channels, bit_depth)
    try:
        props = iio.improps(path)
    except Exception as exc:  # imageio raises many types for unreadable files
        raise DataError(f"{path}: not a readable image (corrupt, truncated, or not PNG/JPEG/EXR)") from exc
    shape = props.shape
    channels = 1 if len(shape) == 2 else shape[-1]
    return ImageHeader(shape[1], shape[0], channels, props.dtype.itemsize * 8)


def _png_palette_has_alpha(path: Path) -> bool:
    with open(path, "rb") as handle:
        reader = png.Reader(file=handle)
        reader.preamble()
        return reader.trns is not None


def read_image_array(path: Path) -> np.ndarray:
    """Decode an image to float32 ``[H,W,C]`` in ``[0,1]`` (file values, not linearised).

    PNGs are read with pypng so 16-bit files keep their precision (Pillow reduces 16-bit RGBA to 8 bits).
    """
    if not path.is_file():
        raise DataError(f"image file not found: {path}")
    try:
        with open(path, "rb") as handle:
            is_png = handle.read(8) == _PNG_SIGNATURE
            if is_png:
                handle.seek(0)
                width, height, rows, info = png.Reader(file=handle).asDirect()
                array = np.vstack([np.asarray(row) for row in rows]).reshape(height, width, info["planes"])
                scale = float(2 ** info["bitdepth"] - 1)
        if not is_png:
            array = iio.imread(path)
            if array.ndim == 2:
                array = array[..., None]
            scale = float(np.iinfo(array.dtype).max) if np.issubdtype(array.dtype, np.integer) else 1.0
    except DataError:
        raise
    except Exception as exc:  # pypng / imageio raise many types for broken files
        raise DataError(f"{path}: cannot decode image, corrupt or truncated ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0] if str(exc) else ''})") from exc
    return (array.astype(np.float32) / scale).clip(0.0, 1.0)


def load_rgba(path: Path, mask_path: Path | None = None,
              premultiplied: bool | None = None) -> tuple[Tensor, Tensor]:
    """Read an sRGB image as linear RGB ``[H,W,3]`` and its mask ``[H,W,1]``.

    The mask is the image's alpha channel, or ``mask_path`` (grey or any channel count: first channel) when
    given; RGB is returned premultiplied by the mask over black. ``premultiplied``: whether the file's RGB
    already is (``True``: kept as stored; ``False``: multiplied by the mask); ``None``: decided from this file
    alone (see :data:`diamond_sss.data.conventions` for the rule and why a capture should declare it).
    """
    array = read_image_array(path)
    channels = array.shape[-1]
    if channels in (1, 2):
        rgb = np.repeat(array[..., :1], 3, axis=-1)
    else:
        rgb = array[..., :3]
    if mask_path is not None:
        mask = read_image_array(mask_path)[..., :1]
        if mask.shape[:2] != array.shape[:2]:
            raise DataError(
                f"{mask_path}: mask size {mask.shape[1]}x{mask.shape[0]} differs from image {path} "
                f"({array.shape[1]}x{array.shape[0]})"
            )
    elif channels in (2, 4):
        mask = array[..., -1:]
    else:
        raise DataError(f"{path}: RGB image without an alpha channel and without a mask file")
    linear = srgb_to_linear(torch.from_numpy(np.ascontiguousarray(rgb)))
    mask_t = torch.from_numpy(np.ascontiguousarray(mask))
    if premultiplied is None:
        premultiplied = _looks_premultiplied(linear, mask_t)
    return (linear if premultiplied else linear * mask_t), mask_t


def _looks_premultiplied(linear: Tensor, mask: Tensor) -> bool:
    """An undeclared file's guess: premultiplied when its RGB is black wherever its mask is (almost) zero."""
    outside = mask[..., 0] < 1e-3
    return bool((linear[outside] <= 1e-6).all()) if outside.any() else True


def composite_background(linear_rgb: Tensor, mask: Tensor, background: str) -> Tensor:
    """Premultiplied linear RGB over a ``"black"`` or ``"white"`` background."""
    if background == "black":
        return linear_rgb
    if background == "white":
        return linear_rgb + (1.0 - mask)
    raise ValueError(f"background must be 'black' or 'white', got {background!r}")


def resize_area(image: Tensor, height: int, width: int) -> Tensor:
    """Area-average resize of a channels-last image ``[H,W,C]`` (exact for integer factors)."""
    if image.shape[0] == height and image.shape[1] == width:
        return image
    chw = image.permute(2, 0, 1).unsqueeze(0)
    return F.interpolate(chw, size=(height, width), mode="area")[0].permute(1, 2, 0).contiguous()


def reframe(images: Tensor, K_from: Tensor, K_to: Tensor, mode: str = "bilinear") -> Tensor:
    """``images [N,C,H,W]`` taken with intrinsics ``K_from [N,3,3]`` as the same cameras (pose and size) with
    ``K_to [N,3,3]`` take them: pixel ``p'`` of the result reads ``p = K_from K_to^-1 p'`` (pixel centres at
    half-integers, :func:`~diamond_sss.data.conventions.pixel_grid`), 0 outside the image. ``mode`` is
    ``grid_sample``'s: ``bilinear`` for images, ``nearest`` for depth maps (no blend of a surface with background).
    Zooming out by ``s = f_from / f_to > 1`` in ``bilinear`` reads ``ceil(s)^2`` points per pixel and averages
    them (a box filter, as :func:`resize_area`), so a small copy does not alias."""
    if images.ndim != 4 or K_from.shape != (images.shape[0], 3, 3) or K_to.shape != K_from.shape:
        raise ValueError(f"need images [N,C,H,W] and K_from / K_to [N,3,3], got {tuple(images.shape)}, "
                         f"{tuple(K_from.shape)} and {tuple(K_to.shape)}")
    focal_from, focal_to = (K[:, :2, :2].diagonal(dim1=-2, dim2=-1) for K in (K_from, K_to))
    if not (bool(torch.isfinite(K_from).all() and torch.isfinite(K_to).all()) and bool((focal_from > 0).all())
            and bool((focal_to > 0).all())):
        raise ValueError(f"K_from / K_to must be finite with positive focal lengths, got fx, fy {focal_from.tolist()} "
                         f"and {focal_to.tolist()}")
    height, width = images.shape[-2:]
    zoom_out = float((focal_from / focal_to).max())
    factor = 1 if mode == "nearest" else max(1, math.ceil(zoom_out - 1e-6))
    mapping = K_from.double() @ torch.linalg.inv(scale_intrinsics(K_to.double(), factor))  # p' (supersampled) -> p
    grid = pixel_grid(factor * height, factor * width, device=images.device).double().reshape(-1, 2)
    source = torch.einsum("nij,pj->npi", mapping, torch.cat([grid, torch.ones_like(grid[:, :1])], dim=-1))
    uv = source[..., :2] / source[..., 2:]
    normalised = torch.stack([uv[..., 0] * (2.0 / width), uv[..., 1] * (2.0 / height)], dim=-1) - 1.0
    out = F.grid_sample(images, normalised.reshape(-1, factor * height, factor * width, 2).to(images.dtype),
                        mode=mode, padding_mode="zeros", align_corners=False)
    return F.avg_pool2d(out, factor) if factor > 1 else out


def to_srgb8(linear_rgb: Tensor, alpha: Tensor | None = None) -> np.ndarray:
    """Linear ``[H,W,3]`` (and optional alpha ``[H,W,1]``) -> uint8 sRGB(A) array.

    With ``alpha`` the file is premultiplied RGBA: colour is set to 0 wherever the stored 8-bit alpha is 0
    (no coverage, no colour), so a file written here (generated images, renders) reads the same whether or not
    its transforms file declares ``premultiplied_alpha`` (:func:`load_rgba`'s guess).
    """
    srgb8 = (linear_to_srgb(linear_rgb.detach().float().cpu()).numpy() * 255.0 + 0.5).astype(np.uint8)
    if alpha is None:
        return srgb8
    alpha8 = (alpha.detach().float().cpu().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
    return np.concatenate([np.where(alpha8 > 0, srgb8, 0).astype(np.uint8), alpha8], axis=-1)


def write_png(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Write a uint8 or uint16 ``[H,W]`` / ``[H,W,C]`` array as PNG, atomically (16-bit through pypng)."""
    array = np.ascontiguousarray(array)
    if array.dtype == np.uint16:
        height, width = array.shape[:2]
        planes = 1 if array.ndim == 2 else array.shape[2]
        mode = {1: "L", 2: "LA", 3: "RGB", 4: "RGBA"}[planes] + ";16"

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as handle:
                png.from_array(array.reshape(height, width * planes), mode).write(handle)

        return atomic_write(path, write)
    if array.dtype != np.uint8:
        raise TypeError(f"write_png expects uint8 or uint16, got {array.dtype}")
    return atomic_write(path, lambda tmp: iio.imwrite(tmp, array, extension=".png"))
