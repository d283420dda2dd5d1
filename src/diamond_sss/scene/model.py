"""A relightable SSS-3DGS scene: Gaussians + SSS residual MLP + global light scale, rendered by deferred shading.

Per image ``b`` (a camera and a point light) and Gaussian ``i``:

1. ``w_v = normalize(c_b - mu_i)``, ``w_l = normalize(p_b - mu_i)``, ``d = |p_b - mu_i|``;
   ``V_SH = clamp(SH_i(w_l) + 0.5, 0, 1)``; with ``sss_light_depth = S > 0`` also ``t_i``, the depth below the
   lit surface from an ``S x S`` depth map rendered at the light (:mod:`diamond_sss.shading.light_depth`).
2. The SSS MLP gives the residual radiance ``R_i`` and the incident light ``L_in,i`` (with
   ``sss_visibility_gradient`` off it sees ``V_SH`` without its gradient: the photometric loss does not train
   ``V_SH``, ``L_raytrace`` does).
3. The G-buffer (normal, base colour, roughness, metallic, s, V_SH, L_in, R) is alpha-blended with the
   Gaussians' per-image features, with expected depth and alpha.
4. :func:`diamond_sss.shading.deferred.deferred_shade` turns it into linear radiance.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from diamond_sss.data.conventions import camera_centers
from diamond_sss.gaussians.model import GaussianModel
from diamond_sss.rendering.rasterize import RasterOutput, rasterize
from diamond_sss.shading.deferred import LIGHT_FALLOFFS, GBuffer, ShadingResult, deferred_shade
from diamond_sss.shading.light_depth import CachedLights, depth_below_surface, light_cameras
from diamond_sss.shading.sh import visibility_from_sh
from diamond_sss.shading.sss_mlp import SSSMLPConfig, SSSResidualMLP, light_geometry
from diamond_sss.utils.compiling import compiled

MATERIAL_OVERRIDES = ("base_color", "roughness", "metallic", "subsurface")


@dataclass
class SceneRender:
    """Everything one render produces: shaded images, the G-buffer and the rasterizer's output."""

    shading: ShadingResult
    gbuffer: GBuffer
    raster: RasterOutput

    @property
    def radiance(self) -> Tensor:
        """Linear radiance ``[B,H,W,3]``, premultiplied over black."""
        return self.shading.radiance


class RelightableScene(nn.Module):
    """Gaussians, the SSS residual MLP and the learnable global light intensity ``exp(log_light_scale)``."""

    def __init__(self, gaussians: GaussianModel, sss_width: int = 32, sss_position_freqs: int = 4,
                 light_init: float = -1.0,
                 scene_center: Tensor | None = None, scene_radius: float = 1.0,
                 mixed_precision: bool = False, light_falloff: str = "none", sss_angular_inputs: bool = False,
                 sss_light_depth: int = 0, sss_visibility_gradient: bool = True) -> None:
        super().__init__()
        if light_falloff not in LIGHT_FALLOFFS:
            raise ValueError(f"light_falloff must be one of {LIGHT_FALLOFFS}, got {light_falloff!r}")
        if sss_light_depth < 0:
            raise ValueError(f"sss_light_depth is a depth map side in px (0: off), got {sss_light_depth}")
        self.gaussians = gaussians
        self.mlp = SSSResidualMLP(SSSMLPConfig(width=sss_width, num_freqs=sss_position_freqs,
                                               angular_inputs=sss_angular_inputs,
                                               light_depth_input=sss_light_depth > 0))
        self.light_depth_size = sss_light_depth
        self.visibility_gradient = sss_visibility_gradient
        self.log_light_scale = nn.Parameter(torch.tensor(float(light_init)))
        self.register_buffer("scene_center", torch.zeros(3) if scene_center is None else scene_center.float().clone())
        self.register_buffer("scene_radius", torch.tensor(float(scene_radius)))
        self.mixed_precision = mixed_precision
        self.light_falloff = light_falloff
        self.compiled_with = "off"
        self._features_fn = RelightableScene._features
        self._shade_fn = deferred_shade

    def compile_shading(self, backend: str) -> None:
        """Run the per-Gaussian features and the deferred shading through ``torch.compile`` with ``backend``
        (:func:`~diamond_sss.utils.compiling.compiled`; ``off``: eager again). The light depth maps and the
        rasterizer between them stay eager."""
        self._features_fn = compiled(RelightableScene._features, backend)  # unbound: a deep copy keeps its own
        self._shade_fn = compiled(deferred_shade, backend)
        self.compiled_with = backend

    @property
    def light_scale(self) -> Tensor:
        return self.log_light_scale.exp()

    def gaussian_features(self, viewmats: Tensor, light_positions: Tensor,
                          overrides: dict[str, float | Tensor] | None = None,
                          cached_lights: CachedLights | None = None) -> Tensor:
        """Per-image, per-Gaussian G-buffer features ``[B,N,14]`` (order of ``GBUFFER_FEATURES``).

        The MLP sees positions, scales and light distances in units of the scene's bounding sphere
        (``(x - c) / r``), so its positional encoding covers about ``[-1, 1]`` whatever the capture's units.
        Under ``mixed_precision`` on CUDA the MLP runs in bfloat16 autocast.
        """
        light_depth = (self.light_depth(light_positions, cached_lights) / self.scene_radius
                       if self.light_depth_size else None)
        return self._features_fn(self, viewmats, light_positions, light_depth, overrides)

    def _features(self, viewmats: Tensor, light_positions: Tensor, light_depth: Tensor | None,
                  overrides: dict[str, float | Tensor] | None) -> Tensor:
        """:meth:`gaussian_features` given the light depth below the surface ``[B,N,1]`` (scene radii; ``None``:
        not an input): no rasterization, so it compiles as one graph."""
        g = self.gaussians
        means = g.means
        batch, num = viewmats.shape[0], means.shape[0]
        geometry = light_geometry(means, camera_centers(viewmats), light_positions)
        visibility = visibility_from_sh(g.visibility_sh, geometry.light_dirs).unsqueeze(-1)
        mlp_visibility = visibility if self.visibility_gradient else visibility.detach()
        normals = g.normals
        radius = self.scene_radius
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=self.mixed_precision and means.is_cuda):
            sss = self.mlp(((means - self.scene_center) / radius).expand(batch, num, 3),
                           g.quats.expand(batch, num, 4), (g.scales / radius).expand(batch, num, 3),
                           geometry.view_dirs, geometry.light_dirs, normals.expand(batch, num, 3), mlp_visibility,
                           geometry.light_distance / radius, light_depth)
        materials = {"base_color": g.base_color, "roughness": g.roughness, "metallic": g.metallic,
                     "subsurface": g.subsurface}
        for name, value in (overrides or {}).items():
            if name not in MATERIAL_OVERRIDES:
                raise ValueError(f"unknown material override '{name}'; choose from {MATERIAL_OVERRIDES}")
            value = torch.as_tensor(value, dtype=means.dtype, device=means.device)
            materials[name] = value.expand_as(materials[name])
        per_gaussian = torch.cat([normals, materials["base_color"], materials["roughness"], materials["metallic"],
                                  materials["subsurface"]], dim=-1)
        return torch.cat([per_gaussian.expand(batch, num, per_gaussian.shape[-1]), visibility,
                          sss.incident.float(), sss.residual.float()], dim=-1)

    @torch.no_grad()
    def light_depth(self, light_positions: Tensor, cached_lights: CachedLights | None = None) -> Tensor:
        """Each Gaussian centre's depth below the surface lit by each light ``[B, N, 1]`` (scene units), from a
        ``light_depth_size``-px depth map rendered at the light (a geometric cue: no gradient), or taken from
        ``cached_lights`` (training: :class:`~diamond_sss.shading.light_depth.LightMapCache`)."""
        g = self.gaussians
        size = self.light_depth_size
        w2c, K = light_cameras(light_positions, self.scene_center, self.scene_radius, size)

        def render(rows: list[int] | slice) -> tuple[Tensor, Tensor]:
            raster = self.render_geometry(w2c[rows], K[rows], size, size)
            return raster.depth, raster.alpha

        if cached_lights is None:
            depth, alpha = render(slice(None))
        else:
            depth, alpha = cached_lights.cache.maps(cached_lights.keys, render)
        return depth_below_surface(g.means, w2c, K, depth, alpha)

    def render(self, viewmats: Tensor, Ks: Tensor, width: int, height: int, light_positions: Tensor,
               light_intensities: Tensor, *, overrides: dict[str, float | Tensor] | None = None,
               backend: str = "auto", cached_lights: CachedLights | None = None) -> SceneRender:
        """Render ``B`` images, image ``b`` seen by camera ``viewmats[b], Ks[b]`` under light ``b``.

        ``viewmats [B,4,4]`` OpenCV w2c, ``Ks [B,3,3]``, ``light_positions [B,3]`` world, ``light_intensities
        [B,3]`` RGB. ``overrides`` replace materials by constants (editing), e.g. ``{"roughness": 0.2}``.
        ``cached_lights``: where the light depth maps come from in training (default: rendered here).
        """
        g = self.gaussians
        features = self.gaussian_features(viewmats, light_positions, overrides, cached_lights)
        raster = rasterize(g.means, g.quats, g.scales, g.opacities, features, viewmats, Ks, width, height,
                           backend=backend)
        gbuffer = GBuffer.from_features(raster.features, raster.depth, raster.alpha)
        shading = self._shade_fn(gbuffer, viewmats, Ks, light_positions, light_intensities, self.light_scale,
                                 self.scene_center if self.light_falloff == "inverse_square" else None)
        return SceneRender(shading=shading, gbuffer=gbuffer, raster=raster)

    def render_geometry(self, viewmats: Tensor, Ks: Tensor, width: int, height: int,
                        backend: str = "auto", centres_only: bool = False) -> RasterOutput:
        """Depth and alpha only (one constant feature channel): the cheap pass of the multi-view losses.

        ``centres_only``: the same images, but gradients reach only the Gaussians' centres; the opacities, scales
        and rotations that set the blending weights ``w_k`` of the expected depth ``sum_k w_k z_k / sum_k w_k``
        are held (detached).
        """
        g = self.gaussians
        ones = torch.ones(g.num_gaussians, 1, device=g.means.device, dtype=g.means.dtype)
        quats, scales, opacities = g.quats, g.scales, g.opacities
        if centres_only:
            quats, scales, opacities = quats.detach(), scales.detach(), opacities.detach()
        return rasterize(g.means, quats, scales, opacities, ones, viewmats, Ks, width, height, backend=backend)
