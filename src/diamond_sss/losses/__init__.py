"""Training objective of DIAMOND-SSS as pure functions.

method.md Sec. 4 and 5; supplement Eq. A.1 - A.7 and Sec. D.
"""

from __future__ import annotations

from diamond_sss.losses.lpips import LPIPS, convert_lpips_state_dict, load_lpips
from diamond_sss.losses.multiview import (
    MultiViewConfig,
    MultiViewTerms,
    multiview_losses,
    multiview_losses_batched,
    sample_foreground_pixels,
    sample_view_pairs,
)
from diamond_sss.losses.photometric import (
    dssim_loss,
    dssim_per_image,
    l1_loss,
    l1_per_image,
    photometric_loss,
    rmse_per_image,
    ssim_per_image,
)
from diamond_sss.losses.regularizers import (
    base_color_prior_loss,
    bilateral_smoothness_loss,
    enhancement_loss,
    enhancement_target,
    enhancement_weight,
    incident_light_loss,
    mask_bce_loss,
    mask_entropy_loss,
    masked_mean,
    normal_consistency_loss,
    normals_from_depth,
    raytrace_visibility_loss,
)

__all__ = [
    "LPIPS",
    "MultiViewConfig",
    "MultiViewTerms",
    "base_color_prior_loss",
    "bilateral_smoothness_loss",
    "convert_lpips_state_dict",
    "dssim_loss",
    "dssim_per_image",
    "enhancement_loss",
    "enhancement_target",
    "enhancement_weight",
    "incident_light_loss",
    "l1_loss",
    "l1_per_image",
    "load_lpips",
    "mask_bce_loss",
    "mask_entropy_loss",
    "masked_mean",
    "multiview_losses",
    "multiview_losses_batched",
    "normal_consistency_loss",
    "normals_from_depth",
    "photometric_loss",
    "raytrace_visibility_loss",
    "rmse_per_image",
    "sample_foreground_pixels",
    "sample_view_pairs",
    "ssim_per_image",
]
