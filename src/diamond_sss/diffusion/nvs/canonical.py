"""The prior's own rig: a capture's world moved so that its cameras sit where the novel-view prior's training cameras
did, before the prior sees them.

The shipped prior was trained on captures of ``diamond-sss synth``'s default light stage (``scripts/make_prior_data.sh``):
the object at the world origin, world +Z up, cameras at distance :data:`PRIOR_CAMERA_RADIUS`. Its conditioning is
not invariant to that frame: the pose token is the cameras' spherical coordinates about the origin (polar angle from
+Z, azimuth, radius; :func:`~diamond_sss.diffusion.nvs.rays.relative_spherical_pose`) and the ray embedding's
moments scale with distance. A capture of another rig (another distance, another up axis, the object off the
origin) is given to the prior in the similarity frame ``x' = s R (x - c)`` (``c`` the object's centre, ``R`` the
rotation taking the cameras' mean up vector to +Z, ``s`` = :data:`PRIOR_CAMERA_RADIUS` / the cameras' median
distance), in which camera ``w2c = [A | t]`` (OpenCV, metric) becomes ``[A R^T | s (A c + t)]`` and metric depth
``z`` becomes ``s z``; images and intrinsics do not change, so the generated images need no mapping back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from diamond_sss.data.conventions import camera_centers

PRIOR_CAMERA_RADIUS = 4.0
"""Distance of the prior's training cameras from the object's centre (``diamond-sss synth --camera-radius``'s
default), scene units."""

PRIOR_FOV_X_DEG = 32.0
"""Horizontal field of view of the priors' training cameras (``diamond-sss synth --fov-x-deg``'s default), degrees."""

PRIOR_FRAME_FILL = math.tan(math.asin(1.0 / PRIOR_CAMERA_RADIUS)) / math.tan(math.radians(PRIOR_FOV_X_DEG) / 2.0)
"""How much of the image's half-width the object's bounding sphere (radius 1) spans in the priors' training images:
``tan(asin(1 / 4)) / tan(16 deg) = 0.90``. Every shipped prior (novel views, relighting, repair) saw objects framed so."""


@dataclass(frozen=True)
class CanonicalFrame:
    """The similarity ``x' = scale * rotation @ (x - center)`` (float64)."""

    rotation: Tensor
    center: Tensor
    scale: float

    def w2c(self, w2c: Tensor) -> Tensor:
        """OpenCV world-to-camera ``[...,4,4]`` in the canonical frame (metric: camera units scaled by ``scale``)."""
        w2c = w2c.double()
        A, t = w2c[..., :3, :3], w2c[..., :3, 3]
        out = w2c.clone()
        out[..., :3, :3] = A @ self.rotation.T
        out[..., :3, 3] = self.scale * (t + (A @ self.center[:, None])[..., 0])
        return out

    def deviation(self) -> tuple[float, float, float]:
        """How far the frame is from the identity: rotation angle (degrees), ``|log scale|`` and the centre's
        distance from the origin relative to :data:`PRIOR_CAMERA_RADIUS` / ``scale`` (the cameras' distance)."""
        angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(self.rotation)) - 1.0) / 2.0))))
        return angle, abs(math.log(self.scale)), float(self.center.norm()) * self.scale / PRIOR_CAMERA_RADIUS


def rotation_between(a: Tensor, b: Tensor) -> Tensor:
    """The least rotation ``[3,3]`` (float64) taking unit vector ``a`` to unit vector ``b`` (Rodrigues); a half turn
    about an axis normal to ``a`` when they are opposite."""
    a, b = a.double() / a.double().norm(), b.double() / b.double().norm()
    v, c = torch.linalg.cross(a, b), float(a @ b)
    if c < -1.0 + 1e-9:
        axis = torch.linalg.cross(a, torch.eye(3, dtype=torch.float64)[int(torch.argmin(a.abs()))])
        axis = axis / axis.norm()
        return 2.0 * torch.outer(axis, axis) - torch.eye(3, dtype=torch.float64)
    skew = torch.tensor([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + skew + skew @ skew / (1.0 + c)


def canonical_frame(w2c: Tensor, center: Tensor, up: Tensor) -> CanonicalFrame:
    """The frame of the cameras ``w2c [N,4,4]`` around the object's ``center [3]`` with world ``up [3]`` (see the
    module docstring)."""
    distance = (camera_centers(w2c.double()) - center.double()).norm(dim=-1).median()
    return CanonicalFrame(rotation_between(up, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)),
                          center.double(), PRIOR_CAMERA_RADIUS / float(distance))
