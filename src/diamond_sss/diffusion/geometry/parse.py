"""``--geometry`` strings: a run folder, ``maps``, ``depth-anything:PATH``, ``marigold:PATH`` or both joined by ``+``."""

from __future__ import annotations

from pathlib import Path

from diamond_sss.diffusion.geometry.base import GeometryError, GeometrySource
from diamond_sss.diffusion.geometry.sources import (
    CombinedGeometry,
    DepthAnythingGeometry,
    MarigoldGeometry,
    RenderedGeometry,
    StoredMapsGeometry,
)

USAGE = (
    "a reconstruction run folder (holding model.safetensors), 'maps' (depth/normal maps stored with the "
    "data), 'depth-anything:PATH', 'marigold:PATH' or 'depth-anything:PATH+marigold:PATH'"
)


def geometry_source(spec: str, device: str = "cpu", seed: int = 0) -> GeometrySource:
    """Parse a ``--geometry`` value; raises :class:`GeometryError` naming the valid forms."""
    spec = spec.strip()
    if not spec:
        raise GeometryError(f"no geometry source given; use {USAGE}")
    if spec == "maps":
        return StoredMapsGeometry()
    if "+" in spec:
        parts = [geometry_source(p, device, seed) for p in spec.split("+")]
        depth = [p for p in parts if isinstance(p, DepthAnythingGeometry)]
        normal = [p for p in parts if isinstance(p, MarigoldGeometry)]
        if len(parts) != 2 or len(depth) != 1 or len(normal) != 1:
            raise GeometryError(f"'{spec}': only 'depth-anything:PATH+marigold:PATH' can be combined")
        return CombinedGeometry(depth[0], normal[0])
    kind, sep, path = spec.partition(":")
    if sep and kind == "depth-anything":
        return DepthAnythingGeometry(Path(path), device=device)
    if sep and kind == "marigold":
        return MarigoldGeometry(Path(path), device=device, seed=seed)
    run = Path(spec)
    if run.is_dir():
        return RenderedGeometry(run, device=device)
    raise GeometryError(f"geometry source '{spec}' is not usable: not an existing run folder; use {USAGE}")
