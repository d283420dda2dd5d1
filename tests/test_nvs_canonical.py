"""The prior's own rig: a capture's cameras moved into the frame the novel-view prior was trained in."""

from __future__ import annotations

import math

import torch

from diamond_sss.data.conventions import (
    camera_centers,
    look_at_opengl_c2w,
    mean_up_vector,
    opengl_c2w_to_opencv_w2c,
    project_points,
)
from diamond_sss.diffusion.nvs.canonical import PRIOR_CAMERA_RADIUS, canonical_frame, rotation_between
from diamond_sss.diffusion.nvs.rays import spherical_coordinates


def _cameras(eyes: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    return opengl_c2w_to_opencv_w2c(look_at_opengl_c2w(eyes, target, up))


def test_rotation_between_known_answers():
    x, y, z = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(rotation_between(x, y) @ x, y, atol=1e-12)
    assert torch.allclose(rotation_between(y, z), torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]],
                                                                dtype=torch.float64), atol=1e-12)
    flip = rotation_between(z, -z)
    assert torch.allclose(flip @ z, -z, atol=1e-12) and torch.allclose(flip @ flip.T, torch.eye(3, dtype=torch.float64))
    assert torch.allclose(rotation_between(z, z), torch.eye(3, dtype=torch.float64))


def test_the_priors_own_rig_is_its_own_canonical_frame():
    angles = torch.linspace(0, 2 * math.pi, 9, dtype=torch.float64)[:-1]
    elevation = torch.tensor(0.45, dtype=torch.float64)
    eyes = 4 * torch.stack([elevation.cos() * angles.cos(), elevation.cos() * angles.sin(),
                            elevation.sin().expand_as(angles)], -1)
    w2c = _cameras(eyes.double(), torch.zeros(3), torch.tensor([0.0, 0, 1]))
    frame = canonical_frame(w2c, torch.zeros(3), mean_up_vector(w2c))
    angle, log_scale, offset = frame.deviation()
    assert angle < 1e-6 and log_scale < 1e-9 and offset == 0.0
    assert torch.allclose(frame.w2c(w2c), w2c.double(), atol=1e-9)


def test_another_rig_moves_onto_the_priors_sphere_and_keeps_its_pixels():
    center, up = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0])
    gen = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(6, 3, generator=gen, dtype=torch.float64), dim=-1)
    dirs[:, 1] = dirs[:, 1].abs() * 0.5  # above the horizon of a +Y-up rig
    dirs = torch.nn.functional.normalize(dirs, dim=-1)
    w2c = _cameras(center + 3.2 * dirs, center, up.double())
    frame = canonical_frame(w2c, center, mean_up_vector(w2c))
    moved = frame.w2c(w2c)
    assert abs(frame.scale - PRIOR_CAMERA_RADIUS / 3.2) < 1e-9
    assert torch.allclose(camera_centers(moved).norm(dim=-1), torch.full((6,), PRIOR_CAMERA_RADIUS,
                                                                          dtype=torch.float64), atol=1e-9)
    assert torch.allclose(mean_up_vector(moved), torch.tensor([0.0, 0, 1], dtype=torch.float64), atol=1e-9)
    # the polar angle about the new origin is the angle from the old up axis
    polar = spherical_coordinates(moved)[..., 0]
    assert torch.allclose(polar.cos(), dirs @ mean_up_vector(w2c), atol=1e-9)
    # a world point and its image in the frame project to the same pixel, at depth scaled by the frame's scale
    points = center + 0.5 * torch.randn(5, 3, generator=gen, dtype=torch.float64)
    moved_points = frame.scale * (frame.rotation @ (points - center).T).T
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]], dtype=torch.float64)
    for original, canonical in zip(w2c.double(), moved):
        uv, z = project_points(points, original, K)
        uv2, z2 = project_points(moved_points, canonical, K)
        assert torch.allclose(uv, uv2, atol=1e-9) and torch.allclose(z2, frame.scale * z, atol=1e-9)
