"""Cook-Torrance GGX microfacet BRDF, UE4 metalness workflow (Karis 2013), as used by SSS-3DGS.

All directions point away from the surface (``l`` towards the light, ``v`` towards the camera) and are
unit vectors. Radiance is linear; ``incident_light`` (``L_in``, unitless transport factor) and
``light_rgb`` (the light's RGB intensity, including any global scale) multiply the BRDF.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

DIELECTRIC_F0 = 0.04
DOT_EPS = 1e-4
MIN_ROUGHNESS = 1e-2


@dataclass
class PBRTerms:
    """Reflected radiance split into its parts, each ``[..., 3]``: ``radiance = diffuse + specular``."""

    diffuse: Tensor
    specular: Tensor
    radiance: Tensor


def ggx_distribution(n_dot_h: Tensor, roughness: Tensor) -> Tensor:
    """GGX / Trowbridge-Reitz normal distribution ``D = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2)``, ``a = r^2``.

    Units 1/sr; normalised so that ``int D(h) (n.h) dw_h = 1`` over the hemisphere. The denominator is
    evaluated as ``(1 - (n.h)^2) + (n.h)^2 a^2`` (same value, no cancellation at ``n.h = 1``).
    """
    a2 = roughness.pow(4)
    cos2 = n_dot_h * n_dot_h
    denom = (1.0 - cos2).clamp_min(0.0) + cos2 * a2
    return a2 / (math.pi * denom * denom)


def smith_g1(n_dot_x: Tensor, roughness: Tensor) -> Tensor:
    """Schlick-GGX masking ``G1(x) = x / (x (1 - k) + k)``, ``k = (r + 1)^2 / 8`` (UE4 analytic lights)."""
    k = (roughness + 1.0).pow(2) / 8.0
    return n_dot_x / (n_dot_x * (1.0 - k) + k)


def geometry_smith(n_dot_v: Tensor, n_dot_l: Tensor, roughness: Tensor) -> Tensor:
    """Separable Smith shadowing-masking ``G = G1(n.v) G1(n.l)`` (unitless, in ``[0, 1]``)."""
    return smith_g1(n_dot_v, roughness) * smith_g1(n_dot_l, roughness)


def fresnel_schlick_ue4(v_dot_h: Tensor, f0: Tensor) -> Tensor:
    """UE4 spherical-Gaussian Schlick Fresnel ``F = F0 + (1 - F0) 2^((-5.55473 v.h - 6.98316) v.h)``."""
    return f0 + (1.0 - f0) * torch.exp2((-5.55473 * v_dot_h - 6.98316) * v_dot_h)


def pbr_shade(
    normal: Tensor,
    view_dir: Tensor,
    light_dir: Tensor,
    base_color: Tensor,
    roughness: Tensor,
    metallic: Tensor,
    incident_light: Tensor,
    light_rgb: Tensor,
    *,
    dot_eps: float = DOT_EPS,
    min_roughness: float = MIN_ROUGHNESS,
) -> PBRTerms:
    """Reflected radiance of one point light, ``L_pbr = (n.l) L_in I_light (f_d + f_s)``.

    ``f_s = D F G / (4 n.v n.l)`` (1/sr), ``f_d = (1 - F)(1 - metallic) base / pi`` (1/sr),
    ``F0 = lerp(0.04, base, metallic)``, ``h = normalize(l + v)``.

    Shapes broadcast: vectors ``[..., 3]``, ``roughness``/``metallic``/``incident_light`` ``[..., 1]``,
    ``base_color``/``light_rgb`` ``[..., 3]``. ``normal`` is normalised here; ``view_dir`` and ``light_dir``
    must be unit. ``n.v`` and ``n.l`` are clamped to ``[dot_eps, 1]`` so the ``1 / (n.v n.l)`` factor and
    its gradient stay finite at grazing angles; the result is exactly zero where ``n.l <= 0`` (light below
    the surface). Roughness is clamped to ``[min_roughness, 1]`` to keep ``D`` finite in float32.
    """
    normal = F.normalize(normal, dim=-1)
    half = F.normalize(light_dir + view_dir, dim=-1)
    raw_n_dot_l = (normal * light_dir).sum(dim=-1, keepdim=True)
    n_dot_l = raw_n_dot_l.clamp(dot_eps, 1.0)
    n_dot_v = (normal * view_dir).sum(dim=-1, keepdim=True).clamp(dot_eps, 1.0)
    n_dot_h = (normal * half).sum(dim=-1, keepdim=True).clamp(0.0, 1.0)
    v_dot_h = (view_dir * half).sum(dim=-1, keepdim=True).clamp(0.0, 1.0)
    roughness = roughness.clamp(min_roughness, 1.0)

    f0 = torch.lerp(torch.full_like(base_color, DIELECTRIC_F0), base_color, metallic)
    fresnel = fresnel_schlick_ue4(v_dot_h, f0)
    specular_brdf = (
        ggx_distribution(n_dot_h, roughness)
        * fresnel
        * geometry_smith(n_dot_v, n_dot_l, roughness)
        / (4.0 * n_dot_v * n_dot_l)
    )
    diffuse_brdf = (1.0 - fresnel) * (1.0 - metallic) * base_color / math.pi

    irradiance = (
        torch.where(raw_n_dot_l > 0.0, n_dot_l, torch.zeros_like(n_dot_l)) * incident_light * light_rgb
    )
    diffuse = irradiance * diffuse_brdf
    specular = irradiance * specular_brdf
    return PBRTerms(diffuse=diffuse, specular=specular, radiance=diffuse + specular)
