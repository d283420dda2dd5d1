"""Geometry conditioning (normalised nearness, camera-space normals, mask) from interchangeable sources."""

from diamond_sss.diffusion.geometry.base import GeometryMaps, GeometrySource
from diamond_sss.diffusion.geometry.parse import geometry_source
from diamond_sss.diffusion.geometry.sources import (
    CombinedGeometry,
    DepthAnythingGeometry,
    MarigoldGeometry,
    RenderedGeometry,
    StoredMapsGeometry,
)

__all__ = [
    "CombinedGeometry",
    "DepthAnythingGeometry",
    "GeometryMaps",
    "GeometrySource",
    "MarigoldGeometry",
    "RenderedGeometry",
    "StoredMapsGeometry",
    "geometry_source",
]
