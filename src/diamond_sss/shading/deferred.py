"""Deferred SSS shading of a rasterized G-buffer (method.md section 3).

Per pixel, with ``x`` the surface point back-projected from the expected depth,
``w_l = normalize(p_light - x)``, ``w_v = normalize(c_cam - x)`` and ``I = light_scale * light_rgb``
(times ``|p_light - c|^2 / |p_light - x|^2`` with ``light_falloff = "inverse_square"``, see below):

    L_pbr = (n.w_l) L_in I (f_d + f_s)            (GGX, UE4 metalness; see :mod:`.ggx`)
    L_sss = R I
    L     = alpha ((1 - s) L_pbr + s L_sss)       (linear radiance, premultiplied over black)

Choices (following the public SSS-3DGS code, where the papers are silent):

* Light transport: the MLP's incident light ``L_in`` is the only shadowing / attenuation factor in
  ``L_pbr``. The blended SH visibility ``V_SH`` does not enter the shading; it is kept in the G-buffer
  for ``L_incident`` (``L1(clamp(L_in), V_SH)``), which ties ``L_in`` to visibility.
* Falloff (``light_falloff``): ``"none"``, as SSS-3DGS (only its debug "simulated point light" mode has
  one): the MLP sees the light distance and must fold the falloff into ``L_in`` and ``R``, per Gaussian,
  from the training lights alone. ``"inverse_square"``: a point light's irradiance, relative to the scene
  centre ``c``: ``I (|p_light - c| / |p_light - x|)^2``, so the global light scale keeps its meaning (the
  intensity at the centre's distance); a capture whose lights lie at different distances from the object
  leaves the ``1 / |p_light - c|^2`` between lights to the MLP and the light scale. The learnable global
  light scale absorbs the capture's units.
* The whole image is linear in the light's intensity: both ``L_pbr`` and the residual ``R`` are scaled
  by ``I``. SSS-3DGS tints ``R`` by the light RGB per Gaussian before blending, which is the same since
  ``I`` is constant over an image.
* No clamping of the result (callers clamp for display and metrics).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import camera_centers, pixel_grid, unproject_pixels
from diamond_sss.shading.ggx import pbr_shade

GBUFFER_FEATURES = (
    ("normal", 3),
    ("base_color", 3),
    ("roughness", 1),
    ("metallic", 1),
    ("subsurface", 1),
    ("visibility", 1),
    ("incident", 1),
    ("residual", 3),
)
GBUFFER_FEATURE_DIM = sum(channels for _, channels in GBUFFER_FEATURES)
LIGHT_FALLOFFS = ("none", "inverse_square")


@dataclass
class GBuffer:
    """Rasterized per-pixel attributes, each ``[B, H, W, c]``.

    Attributes are alpha-normalised surface values (``sum_i w_i a_i / alpha``, like gsplat's expected depth
    ``"ED"``), not premultiplied; build from premultiplied blends with :meth:`from_features`.
    ``normal`` (3, any length, normalised when shading), ``base_color`` (3), ``roughness`` (1),
    ``metallic`` (1), ``subsurface`` (1, ``s``), ``visibility`` (1, ``V_SH`` towards the light),
    ``incident`` (1, ``L_in``), ``residual`` (3, ``R``), ``depth`` (1, camera-space z), ``alpha`` (1).
    """

    normal: Tensor
    base_color: Tensor
    roughness: Tensor
    metallic: Tensor
    subsurface: Tensor
    visibility: Tensor
    incident: Tensor
    residual: Tensor
    depth: Tensor
    alpha: Tensor

    def __post_init__(self) -> None:
        expected = dict(GBUFFER_FEATURES) | {"depth": 1, "alpha": 1}
        lead = self.alpha.shape[:-1]
        for field in fields(self):
            value = getattr(self, field.name)
            if value.dim() != 4 or value.shape[-1] != expected[field.name] or value.shape[:-1] != lead:
                raise ValueError(
                    f"GBuffer.{field.name} must have shape [B, H, W, {expected[field.name]}] matching alpha "
                    f"{tuple(lead)}, got {tuple(value.shape)}"
                )

    @classmethod
    def from_features(
        cls, features: Tensor, depth: Tensor, alpha: Tensor, *, premultiplied: bool = True, eps: float = 1e-6
    ) -> GBuffer:
        """Split a stacked feature map ``[B, H, W, 14]`` (order of ``GBUFFER_FEATURES``) into a GBuffer.

        ``depth`` is the rasterizer's expected depth (already alpha-normalised, gsplat's ``"ED"``) and is
        kept as is. With ``premultiplied=True`` (a plain alpha blend ``sum_i w_i a_i``), the features are
        divided by ``max(alpha, eps)``; pixels with ``alpha <= eps`` get zeros.
        """
        if features.shape[-1] != GBUFFER_FEATURE_DIM:
            raise ValueError(
                f"features must have {GBUFFER_FEATURE_DIM} channels, got {tuple(features.shape)}"
            )
        if premultiplied:
            covered = alpha > eps
            inv_alpha = torch.where(covered, 1.0 / alpha.clamp_min(eps), torch.zeros_like(alpha))
            features = features * inv_alpha
        names = [name for name, _ in GBUFFER_FEATURES]
        parts = features.split([channels for _, channels in GBUFFER_FEATURES], dim=-1)
        return cls(**dict(zip(names, parts)), depth=depth, alpha=alpha)


@dataclass
class ShadingResult:
    """Shaded images ``[B, H, W, 3]`` (linear, premultiplied by alpha) and the surface points.

    ``radiance = (1 - s) pbr + s residual`` with ``pbr = diffuse + specular``; ``residual = R I alpha``.
    ``points``: world-space surface points ``[B, H, W, 3]`` back-projected from the depth.
    """

    radiance: Tensor
    pbr: Tensor
    diffuse: Tensor
    specular: Tensor
    residual: Tensor
    points: Tensor


def backproject_depth(depth: Tensor, w2c: Tensor, K: Tensor) -> Tensor:
    """World points ``x = w2c^-1 (z K^-1 [u, v, 1])`` at every pixel centre. ``[B,H,W,1] -> [B,H,W,3]``."""
    batch, height, width, _ = depth.shape
    uv = pixel_grid(height, width, device=depth.device).to(depth.dtype).reshape(1, -1, 2)
    points = unproject_pixels(uv, depth.reshape(batch, -1), w2c, K)
    return points.reshape(batch, height, width, 3)


def deferred_shade(
    gbuffer: GBuffer,
    w2c: Tensor,
    K: Tensor,
    light_pos: Tensor,
    light_rgb: Tensor,
    light_scale: Tensor,
    falloff_center: Tensor | None = None,
) -> ShadingResult:
    """Shade a G-buffer under one point light per image (see the module docstring for the equations).

    ``w2c [B, 4, 4]`` (OpenCV world-to-camera), ``K [B, 3, 3]`` (pixels), ``light_pos [B, 3]`` (world),
    ``light_rgb [B, 3]`` (the light's RGB intensity), ``light_scale`` (scalar tensor, the global light
    intensity already exponentiated), ``falloff_center [3]`` (world; ``None``: no falloff) the point ``c`` of
    the inverse-square falloff. Differentiable in every input.
    """
    batch = gbuffer.alpha.shape[0]
    for name, value, shape in (
        ("w2c", w2c, (batch, 4, 4)),
        ("K", K, (batch, 3, 3)),
        ("light_pos", light_pos, (batch, 3)),
        ("light_rgb", light_rgb, (batch, 3)),
    ):
        if value.shape != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {tuple(value.shape)}")
    if light_scale.numel() != 1:
        raise ValueError(f"light_scale must be a scalar tensor, got shape {tuple(light_scale.shape)}")

    points = backproject_depth(gbuffer.depth, w2c, K)
    light_dir = F.normalize(light_pos[:, None, None, :] - points, dim=-1)
    view_dir = F.normalize(camera_centers(w2c)[:, None, None, :] - points, dim=-1)
    intensity = (light_scale.reshape(()) * light_rgb)[:, None, None, :]
    if falloff_center is not None:
        to_light = light_pos[:, None, None, :] - points
        center_distance2 = (light_pos - falloff_center).square().sum(-1)[:, None, None, None]
        intensity = intensity * center_distance2 / to_light.square().sum(-1, keepdim=True).clamp_min(1e-12)

    terms = pbr_shade(
        gbuffer.normal,
        view_dir,
        light_dir,
        gbuffer.base_color,
        gbuffer.roughness,
        gbuffer.metallic,
        gbuffer.incident,
        intensity,
    )
    alpha = gbuffer.alpha
    residual = gbuffer.residual * intensity * alpha
    diffuse, specular = terms.diffuse * alpha, terms.specular * alpha
    pbr = diffuse + specular
    s = gbuffer.subsurface
    radiance = (1.0 - s) * pbr + s * residual
    return ShadingResult(
        radiance=radiance, pbr=pbr, diffuse=diffuse, specular=specular, residual=residual, points=points
    )
