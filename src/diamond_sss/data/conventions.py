"""The project's units and conventions, stated once.

Cameras
    * On disk (``transforms_*.json``): ``transform_matrix`` is camera-to-world in OpenGL / Blender axes
      (the camera looks down -Z, +Y is up, +X right).
    * Inside the package: world-to-camera ``w2c`` in OpenCV axes (looks down +Z, +Y down, +X right),
      the convention of ``gsplat.rasterization`` (``viewmats``). Shape ``[..., 4, 4]``, float32.
    * Intrinsics ``K`` are ``[..., 3, 3]`` pixel-unit pinhole matrices. Pixel ``(row i, col j)`` has
      its centre at continuous coordinates ``(u, v) = (j + 0.5, i + 0.5)`` (gsplat's convention), so
      a camera with ``cx = W / 2`` has its principal point in the middle of the image.
    * Depth is camera-space z (metres or scene units), not ray length.

Radiance
    * Linear radiance inside, float32, premultiplied by alpha over a black background.
    * sRGB (IEC 61966-2-1 transfer curve) only on disk and for metrics.
    * RGBA image files: a transforms file's top-level ``"premultiplied_alpha": true`` says its images' RGB is
      premultiplied by alpha (``diamond-sss synth`` writes it: its alpha comes from a separate coverage pass,
      so RGB may be non-zero where alpha is 0); ``false`` says straight alpha (Blender's PNGs), multiplied by
      alpha on loading. Without the key each file is guessed: premultiplied when its RGB is black wherever its
      alpha is 0, straight otherwise (a guess that can differ between the images of one capture). Generated
      images and renders are written premultiplied with no colour where their 8-bit alpha is 0, and the
      pipeline's captures of generated images declare true.

Lights
    * Point lights, world-space position in scene units, RGB intensity (unitless multiplier).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

# OpenGL camera axes -> OpenCV camera axes: flip Y and Z.
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def opengl_c2w_to_opencv_w2c(c2w: Tensor) -> Tensor:
    """Camera-to-world in OpenGL axes -> world-to-camera in OpenCV axes. ``[...,4,4] -> [...,4,4]``.

    ``w2c = (c2w @ diag(1, -1, -1, 1))^-1``.
    """
    flip = _GL_TO_CV.to(dtype=c2w.dtype, device=c2w.device)
    return torch.linalg.inv(c2w @ flip)


def opencv_w2c_to_opengl_c2w(w2c: Tensor) -> Tensor:
    """Inverse of :func:`opengl_c2w_to_opencv_w2c`. ``[...,4,4] -> [...,4,4]``."""
    flip = _GL_TO_CV.to(dtype=w2c.dtype, device=w2c.device)
    return torch.linalg.inv(w2c) @ flip


def look_at_opengl_c2w(eye: Tensor, target: Tensor, up: Tensor | None = None) -> Tensor:
    """OpenGL camera-to-world matrices of cameras at ``eye`` looking at ``target``. ``[..., 3] -> [..., 4, 4]``.

    float64, on ``eye``'s device; ``target`` (and ``up``) broadcast against ``eye``. ``up`` defaults to world +Z;
    for a camera whose viewing direction is (anti)parallel to it, +Y is used.
    """
    eye = eye.to(torch.float64)
    forward = F.normalize(target.to(eye) - eye, dim=-1)
    if up is None:
        world_z, world_y = eye.new_tensor([0.0, 0.0, 1.0]), eye.new_tensor([0.0, 1.0, 0.0])
        up = torch.where((forward @ world_z).abs().unsqueeze(-1) > 0.999, world_y, world_z)
    up = up.to(eye).expand_as(forward)
    right = F.normalize(torch.linalg.cross(forward, up), dim=-1)
    true_up = torch.linalg.cross(right, forward)
    bottom = eye.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(*forward.shape[:-1], 1, 4)
    top = torch.stack([right, true_up, -forward, eye.expand_as(forward)], dim=-1)
    return torch.cat([top, bottom], dim=-2)


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> Tensor:
    """Pinhole matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels, float32 ``[3,3]``."""
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32)


def intrinsics_from_fov(fov_x: float | None, width: int, height: int, fov_y: float | None = None) -> Tensor:
    """Pinhole ``K`` from the horizontal field of view (radians), NeRF-synthetic ``camera_angle_x``.

    ``fx = W / (2 tan(fov_x / 2))``, ``fy = H / (2 tan(fov_y / 2))``; with one of them ``None`` the pixels are
    square (``fy = fx`` or ``fx = fy``); principal point at the image centre ``(W/2, H/2)``.
    """
    if fov_x is None and fov_y is None:
        raise ValueError("intrinsics_from_fov needs fov_x or fov_y")
    fy = None if fov_y is None else 0.5 * height / math.tan(0.5 * fov_y)
    fx = fy if fov_x is None else 0.5 * width / math.tan(0.5 * fov_x)
    fy = fx if fy is None else fy
    return intrinsics_matrix(fx, fy, 0.5 * width, 0.5 * height)


def scale_intrinsics(K: Tensor, factor: float, factor_y: float | None = None) -> Tensor:
    """Intrinsics of an image resized by ``factor`` (``0.5`` halves both sides; ``factor_y``, when given,
    scales the height). ``[...,3,3]``.

    With pixel centres at ``+0.5``, resizing maps continuous coordinates by a pure scale.
    """
    out = K.clone()
    out[..., 0, :] *= factor
    out[..., 1, :] *= factor if factor_y is None else factor_y
    out[..., 2, :] = K[..., 2, :]
    return out


def camera_centers(w2c: Tensor) -> Tensor:
    """World-space camera centres ``C = -R^T t``. ``[...,4,4] -> [...,3]``."""
    rot = w2c[..., :3, :3]
    trans = w2c[..., :3, 3]
    return -(rot.transpose(-1, -2) @ trans.unsqueeze(-1)).squeeze(-1)


def mean_up_vector(w2c: Tensor) -> Tensor:
    """The mean up vector of OpenCV cameras ``w2c [N,4,4]`` (``-`` their y axis in world), unit, float64 ``[3]``;
    world +Z when the mean is shorter than 0.5 (cameras rolled every way)."""
    up = -w2c[:, 1, :3].double().mean(0)
    if float(up.norm()) < 0.5:
        return torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=w2c.device)
    return up / up.norm()


def world_to_camera(points: Tensor, w2c: Tensor) -> Tensor:
    """Transform world points into camera (OpenCV) coordinates. ``[...,N,3], [...,4,4] -> [...,N,3]``."""
    return points @ w2c[..., :3, :3].transpose(-1, -2) + w2c[..., None, :3, 3]


def project_points(points: Tensor, w2c: Tensor, K: Tensor, eps: float = 1e-8) -> tuple[Tensor, Tensor]:
    """Pinhole projection of world points. Returns continuous pixel coordinates ``uv [...,N,2]``
    (``u`` along columns, pixel centres at ``+0.5``) and camera depth ``z [...,N]``.

    ``[u, v, 1]^T z = K X_cam``. Points with ``z <= 0`` get coordinates computed with ``|z| + eps``
    and must be filtered by the caller using ``z``.
    """
    cam = world_to_camera(points, w2c)
    z = cam[..., 2]
    safe_z = z.abs().clamp_min(eps)
    fx, fy = K[..., 0, 0, None], K[..., 1, 1, None]
    cx, cy = K[..., 0, 2, None], K[..., 1, 2, None]
    u = fx * cam[..., 0] / safe_z + cx
    v = fy * cam[..., 1] / safe_z + cy
    return torch.stack([u, v], dim=-1), z


def pixel_grid(height: int, width: int, device: torch.device | str | None = None) -> Tensor:
    """Continuous coordinates of pixel centres, ``[H,W,2]`` with ``(u, v) = (j + 0.5, i + 0.5)``."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=torch.float32) + 0.5,
        torch.arange(width, device=device, dtype=torch.float32) + 0.5,
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)


def unproject_pixels(uv: Tensor, depth: Tensor, w2c: Tensor, K: Tensor) -> Tensor:
    """World points at camera-space depth ``z`` behind pixel coordinates ``uv``.

    ``uv [...,N,2]``, ``depth [...,N]`` (camera z), ``w2c [...,4,4]``, ``K [...,3,3]`` -> ``[...,N,3]``.
    Inverse of :func:`project_points` for ``z > 0``.
    """
    fx, fy = K[..., 0, 0, None], K[..., 1, 1, None]
    cx, cy = K[..., 0, 2, None], K[..., 1, 2, None]
    x = (uv[..., 0] - cx) / fx * depth
    y = (uv[..., 1] - cy) / fy * depth
    cam = torch.stack([x, y, depth], dim=-1)
    rot = w2c[..., :3, :3]
    trans = w2c[..., None, :3, 3]
    return (cam - trans) @ rot


def pixel_ray_directions(w2c: Tensor, K: Tensor, height: int, width: int) -> Tensor:
    """Unit world-space directions of the rays through every pixel centre. ``[H,W,3]``."""
    uv = pixel_grid(height, width, device=w2c.device).reshape(-1, 2)
    ones = torch.ones(uv.shape[0], device=w2c.device, dtype=w2c.dtype)
    points = unproject_pixels(uv, ones, w2c, K)
    dirs = points - camera_centers(w2c)
    return (dirs / dirs.norm(dim=-1, keepdim=True)).reshape(height, width, 3)


def sample_bilinear(image: Tensor, uv: Tensor) -> Tensor:
    """Bilinear lookup of ``image [P,H,W]`` at continuous pixel coordinates ``uv [P,n,2]`` -> ``[P,n]``.

    With the pixel-centre convention above, ``grid_sample(align_corners=False)`` at ``u / W * 2 - 1`` hits
    texel centres exactly; coordinates outside the image read the border value. Differentiable in both inputs.
    """
    height, width = image.shape[-2:]
    grid = torch.stack([uv[..., 0] * (2.0 / width), uv[..., 1] * (2.0 / height)], dim=-1).sub(1.0).unsqueeze(1)
    sampled = F.grid_sample(
        image.unsqueeze(1), grid.to(image.dtype), mode="bilinear", padding_mode="border", align_corners=False
    )
    return sampled[:, 0, 0, :]


def srgb_to_linear(srgb: Tensor) -> Tensor:
    """IEC 61966-2-1 sRGB decoding, values in ``[0, 1]``."""
    srgb = srgb.clamp(0.0, 1.0)
    return torch.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: Tensor) -> Tensor:
    """IEC 61966-2-1 sRGB encoding; input clamped to ``[0, 1]`` first (gradient-safe at 0)."""
    linear = linear.clamp(0.0, 1.0)
    return torch.where(
        linear <= 0.0031308,
        12.92 * linear,
        1.055 * linear.clamp_min(0.0031308) ** (1.0 / 2.4) - 0.055,
    )
