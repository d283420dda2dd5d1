"""The training objective L_total (supplement Eq. A.1-A.7, method.md §4-§5), assembled from the pure terms.

    L_total = [(1 - l_dssim) E + l_dssim (1 - SSIM)]_w + l_lpips LPIPS_w + l_mask L_mask
              + l_mask_entropy H(alpha) + sum_q l_smooth^q L_smooth^q + l_enh L_enh + l_base_color L_bc
              + l_normal L_normals + l_incident L_incident + l_visibility L_raytrace
              + l_sil L_sil^MV + l_depth L_depth^MV

``[.]_w``: per-image weighted (1 for real images, the pipeline's ``synthetic_weight`` = alpha for generated
ones). ``E`` is each image's L1 (Eq. A.1) or RMSE (``losses.photometric_error``). ``E`` and D-SSIM compare sRGB values
(``losses.photometric_space``, or linear radiance), LPIPS sRGB, the regularisers linear radiance. Geometric terms (mask, normals, multi-view) use every image at full weight.
With a background ``b`` (``shading.random_background``) the photometric and LPIPS terms compare ``L + (1 - alpha) b``
with ``I + (1 - M) b`` (render and target over the same colour); the regularisers see the target over black.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.losses import photometric, regularizers
from diamond_sss.losses.lpips import LPIPS
from diamond_sss.losses.photometric import weighted_mean
from diamond_sss.scene.model import SceneRender
from diamond_sss.training.config import TrainConfig

SMOOTHED_ATTRIBUTES = {
    "base_color": "lambda_base_color_smooth",
    "roughness": "lambda_roughness_smooth",
    "metallic": "lambda_metallic_smooth",
    "subsurface": "lambda_subsurfacedness_smooth",
}


@dataclass
class TargetBatch:
    """Ground truth of a batch: linear RGB over black ``[B,H,W,3]``, masks ``[B,H,W,1]``, per-image weights ``[B]``,
    cameras, and the background colour ``[B,1,1,3]`` the photometric terms composite both images over (None: black)."""

    rgb: Tensor
    mask: Tensor
    weights: Tensor
    viewmats: Tensor
    Ks: Tensor
    background: Tensor | None = None


def image_objective(render: SceneRender, target: TargetBatch, cfg: TrainConfig,
                    lpips_model: LPIPS | None) -> dict[str, Tensor]:
    """Weighted loss terms of one batch (each already multiplied by its lambda), by name."""
    terms: dict[str, Tensor] = {}
    gb = render.gbuffer
    pred, observed = render.radiance, target.rgb
    if target.background is not None:
        pred = pred + (1.0 - gb.alpha) * target.background
        observed = observed + (1.0 - target.mask) * target.background
    if cfg.losses.photometric_space == "srgb":
        compared, reference = linear_to_srgb(pred), linear_to_srgb(observed)
    else:
        compared, reference = pred, observed
    terms["photometric"] = photometric.photometric_loss(compared, reference, cfg.losses.lambda_dssim, target.weights,
                                                        cfg.losses.photometric_error)
    if lpips_model is not None and cfg.losses.lambda_lpips > 0:
        distance = lpips_model(linear_to_srgb(pred), linear_to_srgb(observed))
        terms["lpips"] = cfg.losses.lambda_lpips * weighted_mean(distance, target.weights)
    mask = target.mask
    if cfg.losses.lambda_mask > 0:
        terms["mask"] = cfg.losses.lambda_mask * regularizers.mask_bce_loss(gb.alpha, mask)
    if cfg.losses.lambda_mask_entropy > 0:
        terms["mask_entropy"] = cfg.losses.lambda_mask_entropy * regularizers.mask_entropy_loss(gb.alpha)
    edges = None  # the image's edge weights, taken once for every smoothed attribute
    for name, key in SMOOTHED_ATTRIBUTES.items():
        weight = getattr(cfg.losses, key)
        if weight > 0:
            attribute = getattr(gb, name)
            edges = edges or regularizers.edge_weights(target.rgb, mask, like=attribute)
            terms[f"smooth_{name}"] = weight * regularizers.bilateral_smoothness_loss(attribute, target.rgb, mask,
                                                                                      edges)
    if cfg.losses.lambda_enh > 0:
        terms["enhance"] = cfg.losses.lambda_enh * regularizers.enhancement_loss(gb.base_color, target.rgb, mask)
    if cfg.losses.lambda_base_color > 0:
        terms["base_color"] = cfg.losses.lambda_base_color * regularizers.base_color_prior_loss(
            gb.base_color, target.rgb, mask)
    if cfg.losses.lambda_normal > 0:
        pseudo = regularizers.normals_from_depth(gb.depth, target.viewmats, target.Ks)
        terms["normal"] = cfg.losses.lambda_normal * regularizers.normal_consistency_loss(
            torch.nn.functional.normalize(gb.normal, dim=-1), pseudo, mask * (gb.alpha.detach() > 0.5))
    if cfg.losses.lambda_incident_light > 0:
        terms["incident"] = cfg.losses.lambda_incident_light * regularizers.incident_light_loss(
            gb.incident, gb.visibility, mask)
    return terms
