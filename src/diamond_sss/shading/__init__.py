"""Deferred SSS shading: SH visibility, GGX BRDF, residual MLP, deferred shading, ray-traced visibility, light depth."""

from __future__ import annotations

from diamond_sss.shading.deferred import (
    GBUFFER_FEATURE_DIM,
    GBUFFER_FEATURES,
    GBuffer,
    ShadingResult,
    backproject_depth,
    deferred_shade,
)
from diamond_sss.shading.ggx import (
    PBRTerms,
    fresnel_schlick_ue4,
    geometry_smith,
    ggx_distribution,
    pbr_shade,
    smith_g1,
)
from diamond_sss.shading.light_depth import depth_below_surface, light_cameras
from diamond_sss.shading.raytrace import (
    VisibilitySamples,
    gaussian_transmittance,
    ray_gaussian_max_response,
    raytraced_visibility,
    sample_uniform_sphere,
)
from diamond_sss.shading.sh import eval_sh, light_sh_encoding, num_sh_bases, sh_basis, visibility_from_sh
from diamond_sss.shading.sss_mlp import (
    LightGeometry,
    SSSMLPConfig,
    SSSOutput,
    SSSResidualMLP,
    light_geometry,
    positional_encoding,
)

__all__ = [
    "GBUFFER_FEATURES",
    "GBUFFER_FEATURE_DIM",
    "GBuffer",
    "LightGeometry",
    "PBRTerms",
    "SSSMLPConfig",
    "SSSOutput",
    "SSSResidualMLP",
    "ShadingResult",
    "VisibilitySamples",
    "backproject_depth",
    "deferred_shade",
    "depth_below_surface",
    "eval_sh",
    "fresnel_schlick_ue4",
    "gaussian_transmittance",
    "geometry_smith",
    "ggx_distribution",
    "light_cameras",
    "light_geometry",
    "light_sh_encoding",
    "num_sh_bases",
    "pbr_shade",
    "positional_encoding",
    "ray_gaussian_max_response",
    "raytraced_visibility",
    "sample_uniform_sphere",
    "sh_basis",
    "smith_g1",
    "visibility_from_sh",
]
