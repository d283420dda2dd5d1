"""Light-stage geometry: cameras and point lights on spheres around the object (world Z-up, origin centre).

Cameras and lights each lie on a Fibonacci spiral restricted to a band of heights ``z / r in [z_min, z_max]``
(golden-angle azimuth steps, a seeded random azimuth offset). One spiral of ``n_train + n_test`` points
is drawn per kind and every ``(n_train + n_test) / n_test``-th point goes to the test split, so test
cameras and lights are novel positions interleaved between the training ones, never equal to them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from diamond_sss.data.conventions import look_at_opengl_c2w

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass(frozen=True)
class LightStageConfig:
    """Sizes and placement of the capture rig (scene units, object inside the unit sphere).

    Bands are heights ``z / r`` (``-0.5``: 30 degrees below the horizon). ``lights_per_view`` K: each training
    view is lit by a seeded random K of the training lights (an incomplete lattice, :func:`view_light_subsets`);
    ``None``: by every light.
    """

    views: int = 40
    lights: int = 24
    test_views: int = 8
    test_lights: int = 6
    camera_radius: float = 4.0
    light_radius: float = 5.0
    fov_x_deg: float = 32.0
    camera_band: tuple[float, float] = (-0.35, 0.85)
    light_band: tuple[float, float] = (-0.5, 0.95)
    seed: int = 0
    lights_per_view: int | None = None

    def __post_init__(self) -> None:
        if self.views < 1 or self.lights < 1:
            raise ValueError(f"need at least one view and one light, got {self.views} x {self.lights}")
        if self.test_views < 0 or self.test_lights < 0:
            raise ValueError("test_views and test_lights must be >= 0")
        if self.camera_radius <= 1.0 or self.light_radius <= 1.0:
            raise ValueError("camera_radius and light_radius must exceed the object radius 1")
        for band in (self.camera_band, self.light_band):
            if not -1.0 <= band[0] < band[1] <= 1.0:
                raise ValueError(f"a height band must satisfy -1 <= z_min < z_max <= 1, got {band}")
        if self.lights_per_view is not None and not 1 <= self.lights_per_view <= self.lights:
            raise ValueError(f"lights_per_view must be in 1..{self.lights} (the training lights), "
                             f"got {self.lights_per_view}")


@dataclass(frozen=True)
class LightStage:
    """Camera-to-world matrices (OpenGL axes) ``[V,4,4]`` and light positions ``[L,3]`` per split."""

    train_c2w: np.ndarray
    test_c2w: np.ndarray
    train_lights: np.ndarray
    test_lights: np.ndarray
    fov_x: float


def fibonacci_band(n: int, radius: float, band: tuple[float, float], azimuth_offset: float) -> np.ndarray:
    """``n`` near-uniform points on the sphere of ``radius`` with ``z / radius`` in ``band``. ``[n,3]``.

    ``z_k = z_max - (k + 1/2) (z_max - z_min) / n``, ``phi_k = k * golden_angle + offset``.
    """
    k = np.arange(n, dtype=np.float64)
    z = band[1] - (k + 0.5) * (band[1] - band[0]) / n
    rho = np.sqrt(np.clip(1.0 - z**2, 0.0, None))
    phi = k * GOLDEN_ANGLE + azimuth_offset
    return radius * np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)


def interleaved_test_indices(n_total: int, n_test: int) -> np.ndarray:
    """Evenly spread indices ``floor((i + 1/2) n_total / n_test)`` of ``n_test`` points among ``n_total``."""
    if n_test == 0:
        return np.zeros(0, dtype=np.int64)
    return np.floor((np.arange(n_test) + 0.5) * n_total / n_test).astype(np.int64)


def split_spiral(
    n_train: int, n_test: int, radius: float, band: tuple[float, float], offset: float
) -> tuple[np.ndarray, np.ndarray]:
    """Train and test point sets from one spiral of ``n_train + n_test`` points."""
    points = fibonacci_band(n_train + n_test, radius, band, offset)
    test_idx = interleaved_test_indices(n_train + n_test, n_test)
    is_test = np.zeros(len(points), dtype=bool)
    is_test[test_idx] = True
    return points[~is_test], points[is_test]


def view_light_subsets(config: LightStageConfig) -> list[list[int]]:
    """Per training view, the sorted training-light indices that light it.

    Every light when ``lights_per_view`` is ``None``; else K lights drawn without replacement by a generator
    seeded with ``(config.seed, view)``, so a view's subset depends only on the seed and the view index.
    """
    if config.lights_per_view is None:
        return [list(range(config.lights)) for _ in range(config.views)]
    return [sorted(int(light) for light in np.random.default_rng([config.seed, view]).choice(
        config.lights, config.lights_per_view, replace=False)) for view in range(config.views)]


def cameras_looking_at_origin(eyes: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world matrices ``[N,4,4]`` of cameras at ``eyes [N,3]`` looking at the origin, Z up."""
    target = torch.zeros(3, dtype=torch.float64)
    mats = [look_at_opengl_c2w(torch.from_numpy(eye), target).numpy() for eye in eyes]
    return np.stack(mats) if mats else np.zeros((0, 4, 4))


def build_light_stage(config: LightStageConfig) -> LightStage:
    """Cameras and lights for both splits, deterministic under ``config.seed``."""
    rng = np.random.default_rng(config.seed)
    cam_offset, light_offset = rng.uniform(0.0, 2.0 * math.pi, size=2)
    train_eyes, test_eyes = split_spiral(
        config.views, config.test_views, config.camera_radius, config.camera_band, cam_offset
    )
    train_lights, test_lights = split_spiral(
        config.lights, config.test_lights, config.light_radius, config.light_band, light_offset
    )
    return LightStage(
        train_c2w=cameras_looking_at_origin(train_eyes),
        test_c2w=cameras_looking_at_origin(test_eyes),
        train_lights=train_lights,
        test_lights=test_lights,
        fov_x=math.radians(config.fov_x_deg),
    )
