"""Per-Gaussian subsurface-scattering residual MLP (SSS-3DGS, method.md section 2)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def positional_encoding(x: Tensor, num_freqs: int) -> Tensor:
    """NeRF positional encoding ``[x, sin(2^k pi x), cos(2^k pi x)]_{k<F}``. ``[..., D] -> [..., D(1 + 2F)]``.

    Layout: the raw input first, then for each frequency ``k`` the sines of all ``D`` components followed
    by their cosines. Inputs are expected in scene units normalised to roughly ``[-1, 1]``.
    """
    if num_freqs < 0:
        raise ValueError(f"num_freqs must be >= 0, got {num_freqs}")
    freqs = math.pi * 2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)
    angles = (x.unsqueeze(-2) * freqs.unsqueeze(-1)).flatten(-2)
    per_freq = torch.stack([angles.sin(), angles.cos()], dim=-2)
    per_freq = per_freq.unflatten(-1, (num_freqs, x.shape[-1])).transpose(-3, -2).flatten(-3)
    return torch.cat([x, per_freq], dim=-1)


@dataclass
class LightGeometry:
    """Per-Gaussian directions for the MLP, batched over ``B`` camera/light pairs.

    ``view_dirs``/``light_dirs``: unit vectors from each centre towards the camera/light ``[B, N, 3]``;
    ``light_distance``: ``|p_light - mu|`` in scene units ``[B, N, 1]``.
    """

    view_dirs: Tensor
    light_dirs: Tensor
    light_distance: Tensor


def light_geometry(means: Tensor, camera_center: Tensor, light_pos: Tensor) -> LightGeometry:
    """``w_v = normalize(c - mu)``, ``w_l = normalize(p - mu)``, ``d_l = |p - mu|``.

    ``means [N, 3]``, ``camera_center [B, 3]``, ``light_pos [B, 3]`` (world) -> :class:`LightGeometry`.
    """
    if means.dim() != 2 or means.shape[-1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    if camera_center.shape != light_pos.shape or camera_center.dim() != 2 or camera_center.shape[-1] != 3:
        raise ValueError(
            f"camera_center and light_pos must both be [B, 3], got {tuple(camera_center.shape)} "
            f"and {tuple(light_pos.shape)}"
        )
    to_light = light_pos[:, None, :] - means[None]
    distance = to_light.norm(dim=-1, keepdim=True)
    return LightGeometry(
        view_dirs=F.normalize(camera_center[:, None, :] - means[None], dim=-1),
        light_dirs=to_light / distance.clamp_min(1e-12),
        light_distance=distance,
    )


@dataclass
class SSSMLPConfig:
    """Architecture of :class:`SSSResidualMLP`.

    ``incident_bias_init`` is the initial bias of the ``L_in`` output so that the incident light starts
    near 1 (unoccluded, the ReLU active) instead of at a dead zero. ``angular_inputs`` appends the cosines
    ``n.w_l``, ``n.w_v`` and ``w_v.w_l`` to the inputs, so that a dependence on the light's angle to the surface is
    one function for every Gaussian instead of one learnt per position from the training lights.
    ``light_depth_input`` appends the depth below the lit surface along the light ray (scene radii; see
    :mod:`diamond_sss.shading.light_depth`), which the caller computes from the geometry for each light.
    """

    width: int = 32
    num_hidden_layers: int = 3
    num_freqs: int = 4
    negative_slope: float = 0.01
    incident_bias_init: float = 1.0
    angular_inputs: bool = False
    light_depth_input: bool = False


@dataclass
class SSSOutput:
    """MLP outputs per Gaussian (and per camera/light when batched).

    ``residual``: subsurface residual radiance ``R`` in ``[0, 1]``, ``[..., N, 3]`` (scaled by the light's
    RGB intensity at shading time). ``incident``: incident light transport ``L_in >= 0``, ``[..., N, 1]``
    (one channel shared by R, G, B, as in SSS-3DGS).
    """

    residual: Tensor
    incident: Tensor


class SSSResidualMLP(nn.Module):
    """``(PE(x), q, s, w_v, w_l, n, V, d_l) -> (R, L_in)`` with a LeakyReLU trunk and two heads.

    Inputs (leading shape ``[N]`` or ``[B, N]``; per-Gaussian ``[N, ...]`` tensors broadcast against
    per-camera/light ``[B, N, ...]`` ones): ``positions [..., 3]`` (positionally encoded with
    ``num_freqs`` frequencies plus the raw value), ``quats [..., 4]`` (normalised here), ``scales [..., 3]``
    (activated, i.e. ``exp(log_scale)``), ``view_dirs``/``light_dirs``/``normals [..., 3]`` (normalised
    here), ``visibility [..., 1]`` (towards the light, in ``[0, 1]``), ``light_distance [..., 1]`` and
    ``light_depth [..., 1]`` (required with ``light_depth_input``, else ignored). ``RelightableScene`` passes
    positions as ``(mu - c) / r`` and scales, light distances and depths in scene radii ``r``.
    Heads: ``R = sigmoid(W h)`` (RGB) and ``L_in = relu(W' leaky(W'' h))`` (one channel).
    """

    def __init__(self, config: SSSMLPConfig | None = None) -> None:
        super().__init__()
        self.config = config or SSSMLPConfig()
        cfg = self.config
        if cfg.width <= 0 or cfg.num_hidden_layers <= 0:
            raise ValueError(f"width and num_hidden_layers must be positive, got {cfg}")
        layers: list[nn.Module] = []
        in_features = self.input_dim
        for _ in range(cfg.num_hidden_layers):
            layers += [nn.Linear(in_features, cfg.width), nn.LeakyReLU(cfg.negative_slope)]
            in_features = cfg.width
        self.trunk = nn.Sequential(*layers)
        self.residual_head = nn.Linear(cfg.width, 3)
        self.incident_head = nn.Sequential(
            nn.Linear(cfg.width, cfg.width), nn.LeakyReLU(cfg.negative_slope), nn.Linear(cfg.width, 1)
        )
        nn.init.constant_(self.incident_head[-1].bias, cfg.incident_bias_init)

    @property
    def input_dim(self) -> int:
        """Width of the concatenated input: ``3 (1 + 2F)`` position + 4 + 3 + 3 + 3 + 3 + 1 + 1 (+ 3 cosines)
        (+ 1 depth below the lit surface)."""
        cfg = self.config
        angular, depth = 3 * cfg.angular_inputs, int(cfg.light_depth_input)
        return 3 * (1 + 2 * cfg.num_freqs) + 4 + 3 + 3 + 3 + 3 + 1 + 1 + angular + depth

    def forward(
        self,
        positions: Tensor,
        quats: Tensor,
        scales: Tensor,
        view_dirs: Tensor,
        light_dirs: Tensor,
        normals: Tensor,
        visibility: Tensor,
        light_distance: Tensor,
        light_depth: Tensor | None = None,
    ) -> SSSOutput:
        if self.config.light_depth_input and light_depth is None:
            raise ValueError("this MLP was built with light_depth_input=True and needs light_depth [..., 1]")
        inputs = {
            "positions": (positions, 3),
            "quats": (quats, 4),
            "scales": (scales, 3),
            "view_dirs": (view_dirs, 3),
            "light_dirs": (light_dirs, 3),
            "normals": (normals, 3),
            "visibility": (visibility, 1),
            "light_distance": (light_distance, 1),
        }
        if self.config.light_depth_input:
            inputs["light_depth"] = (light_depth, 1)
        for name, (tensor, channels) in inputs.items():
            if tensor.shape[-1] != channels or tensor.dim() not in (2, 3):
                raise ValueError(
                    f"{name} must have shape [N, {channels}] or [B, N, {channels}], got {tuple(tensor.shape)}"
                )
        lead = torch.broadcast_shapes(*(tensor.shape[:-1] for tensor, _ in inputs.values()))
        view, light, normal = (F.normalize(v, dim=-1) for v in (view_dirs, light_dirs, normals))
        features = [
            positional_encoding(positions, self.config.num_freqs),
            F.normalize(quats, dim=-1),
            scales,
            view,
            light,
            normal,
            visibility,
            light_distance,
        ]
        if self.config.angular_inputs:
            normal, view, light = torch.broadcast_tensors(normal, view, light)
            features.append(torch.stack([(normal * light).sum(-1), (normal * view).sum(-1), (view * light).sum(-1)], -1))
        if self.config.light_depth_input:
            features.append(light_depth)
        x = torch.cat([f.expand(*lead, f.shape[-1]) for f in features], dim=-1)
        hidden = self.trunk(x)
        return SSSOutput(
            residual=torch.sigmoid(self.residual_head(hidden)),
            incident=F.relu(self.incident_head(hidden)),
        )
