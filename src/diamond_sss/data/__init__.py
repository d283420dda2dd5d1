"""OLAT data: conventions, the transforms-JSON reader, the lattice dataset and capture regimes."""

from diamond_sss.data.dataset import (
    Camera,
    ImageSample,
    Light,
    Observation,
    OLATDataset,
    SceneBounds,
    scene_bounds,
)
from diamond_sss.data.regimes import RegimeSelection, select_regime
from diamond_sss.errors import DataError

__all__ = [
    "Camera",
    "DataError",
    "ImageSample",
    "Light",
    "OLATDataset",
    "Observation",
    "RegimeSelection",
    "SceneBounds",
    "scene_bounds",
    "select_regime",
]
