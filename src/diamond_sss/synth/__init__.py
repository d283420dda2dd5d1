"""Physically based synthetic OLAT captures of translucent objects (Mitsuba 3)."""

from __future__ import annotations

from diamond_sss.synth.materials import MATERIALS, TranslucentMaterial, get_material, material_names
from diamond_sss.synth.scene import LightStage, LightStageConfig, build_light_stage
from diamond_sss.synth.shapes import SHAPES, TriangleMesh, build_shape, shape_names

__all__ = [
    "MATERIALS",
    "SHAPES",
    "LightStage",
    "LightStageConfig",
    "TranslucentMaterial",
    "TriangleMesh",
    "build_light_stage",
    "build_shape",
    "get_material",
    "material_names",
    "shape_names",
]
