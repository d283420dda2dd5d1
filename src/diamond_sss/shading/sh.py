"""Real spherical harmonics up to degree 3, in the 3DGS / gsplat convention.

The basis is the real, orthonormal SH basis with the Condon-Shortley phase folded into the signs used by
3DGS and ``gsplat`` (``Y_1 = -C1 y, Y_2 = C1 z, Y_3 = -C1 x``, ...). Index ``l^2 + l + m`` holds
``Y_l^m`` for ``m = -l..l``. Directions are normalised before evaluation, so any non-zero vector works.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of basis functions up to ``degree``: ``(degree + 1)^2``."""
    return (degree + 1) ** 2


def sh_degree_from_num_bases(num_bases: int) -> int:
    """Inverse of :func:`num_sh_bases`; raises for counts that are not ``1, 4, 9, 16``."""
    degree = math.isqrt(num_bases) - 1
    if num_sh_bases(degree) != num_bases or not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH coefficient count must be one of 1, 4, 9, 16, got {num_bases}")
    return degree


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Real SH basis ``Y_k(w)`` at the directions ``dirs [..., 3]`` -> ``[..., (degree + 1)^2]`` (unitless).

    Orthonormal on the unit sphere: ``int Y_i Y_j dw = delta_ij``.
    """
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in [0, {MAX_SH_DEGREE}], got {degree}")
    if dirs.shape[-1] != 3:
        raise ValueError(f"dirs must have shape [..., 3], got {tuple(dirs.shape)}")
    x, y, z = F.normalize(dirs, dim=-1).unbind(-1)
    bases = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        bases += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        bases += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        bases += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(bases, dim=-1)


def eval_sh(coeffs: Tensor, dirs: Tensor) -> Tensor:
    """One-channel SH function ``f(w) = sum_k c_k Y_k(w)``. ``coeffs [...,K]``, ``dirs [...,3]`` -> ``[...]``.

    ``K`` is 1, 4, 9 or 16 (degree 0-3); leading dimensions broadcast.
    """
    degree = sh_degree_from_num_bases(coeffs.shape[-1])
    return (coeffs * sh_basis(dirs, degree)).sum(dim=-1)


def visibility_from_sh(coeffs: Tensor, dirs: Tensor) -> Tensor:
    """SH visibility ``V_SH(w) = clamp(f(w) + 0.5, 0, 1)`` (fraction of light arriving). ``[...,K] -> [...]``.

    The ``+0.5`` offset makes all-zero coefficients mean "half visible", as in SSS-3DGS.
    """
    return (eval_sh(coeffs, dirs) + 0.5).clamp(0.0, 1.0)


def light_sh_encoding(dirs: Tensor, degree: int = 2) -> Tensor:
    """SH code of a light direction for the relighting diffusion model: ``Y_k(w_l)``, ``[...,3] -> [...,9]``.

    Just the basis (degree 2 gives the 9-D code); ``dirs`` need not be unit length.
    """
    return sh_basis(dirs, degree)
