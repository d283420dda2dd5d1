"""The repair model's input at a target camera and light: the reconstruction's render there and the nearest real
image under the same light, forward-warped into the target.

For target view ``v`` and light ``l`` (``[23, H, W]``, :data:`~.config.INPUT_CHANNELS`):

    render   srgb(R_v,l) (3, premultiplied), alpha (1), (z - near) / (far - near) alpha (1),
             camera-space normals n alpha (3), max(0, n . (p_l - x) / |p_l - x|) alpha (1)
    warped   srgb(I_s,l) forward-warped from real view s (the real camera under light l nearest to v in direction
             from the object's centre) with the render's depth at s (3), and where the warp landed (1)
    light    light_code(p_l, w2c_v, centre, radius) (10), constant over the image

``x`` is the surface point the render's depth unprojects to; ``near`` / ``far`` the capture's depth range
(:class:`~diamond_sss.data.dataset.SceneBounds`). Without a real image under ``l`` the warped channels are 0.
With ``size`` the target is made at most ``size`` pixels on its longer side (the camera's image resized, the
intrinsics scaled): the model's training size, so that it sees the object at the scale it learnt on.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from diamond_sss.data.conventions import linear_to_srgb, pixel_grid, unproject_pixels
from diamond_sss.data.dataset import OLATDataset, directions_from
from diamond_sss.diffusion.geometry.base import world_to_camera_normals
from diamond_sss.diffusion.nvs.warp import forward_warp
from diamond_sss.diffusion.relight.light import light_code
from diamond_sss.runs.folder import render_lattice_image
from diamond_sss.scene.model import RelightableScene, SceneRender

SURFACE_ALPHA = 0.5
"""Render pixels with at least this alpha have a surface: their depth is warped and unprojected."""


def render_channels(render: SceneRender, w2c: Tensor, K: Tensor, light_position: Tensor, near: float,
                    far: float) -> Tensor:
    """The 9 render channels ``[9, H, W]`` of one render (batch of 1) seen by ``w2c [4,4]``, ``K [3,3]`` under
    the light at ``light_position [3]`` (world units)."""
    g = render.gbuffer
    alpha = g.alpha[0].permute(2, 0, 1).clamp(0, 1)
    rgb = linear_to_srgb(render.radiance[0].clamp(0, 1)).permute(2, 0, 1)
    depth = g.depth[0, ..., 0]
    height, width = depth.shape
    surface = g.alpha[0, ..., 0] >= SURFACE_ALPHA
    normals = torch.nn.functional.normalize(g.normal[0], dim=-1, eps=1e-8)
    uv = pixel_grid(height, width, device=depth.device).reshape(-1, 2).to(w2c)
    points = unproject_pixels(uv, depth.reshape(-1).to(w2c), w2c, K).reshape(height, width, 3)
    to_light = torch.nn.functional.normalize(light_position.to(points) - points, dim=-1, eps=1e-8)
    n_dot_l = (normals * to_light).sum(-1).clamp_min(0) * surface
    depth_01 = ((depth - near) / max(far - near, 1e-6)).clamp(0, 1) * surface
    normals_cam = world_to_camera_normals(normals[None], w2c[None])[0].permute(2, 0, 1) * alpha
    return torch.cat([rgb, alpha, depth_01[None], normals_cam, n_dot_l[None]]).float()


class RepairInputs:
    """Builds :func:`target` inputs on the cameras and lights of ``lattice`` from ``scene`` and the real images
    ``real_indices`` of ``real`` (the images ``scene`` was trained on; their view and light indices are the
    lattice's, as :func:`~diamond_sss.pipeline.rig.write_lattice` keeps them; they are warped from ``real``'s
    cameras). Each real view's depth is rendered once."""

    def __init__(self, scene: RelightableScene, lattice: OLATDataset, real: OLATDataset,
                 real_indices: Sequence[int], size: int | None = None) -> None:
        self.scene, self.lattice, self.real, self.size = scene, lattice, real, size
        bounds = lattice.bounds
        self.center, self.radius, self.near, self.far = bounds.center, bounds.radius, bounds.near, bounds.far
        self.view_dirs = directions_from(lattice.camera_centers, self.center)
        self.real_of_light: dict[int, list[int]] = {}
        for index in real_indices:
            self.real_of_light.setdefault(real.observations[index].light, []).append(int(index))
        self._depth: dict[int, Tensor] = {}

    def scale(self, view: int) -> float:
        """The factor lattice view ``view``'s image is resized by for the model (1: its own size)."""
        camera = self.lattice.cameras[view]
        longer = max(camera.width, camera.height)
        return 1.0 if self.size is None or longer <= self.size else self.size / longer

    def render(self, view: int, light: int) -> SceneRender:
        """The scene rendered at lattice view ``view`` under lattice light ``light``, at the model's size."""
        return render_lattice_image(self.scene, self.lattice, view, light, self.scale(view))

    def source(self, view: int, light: int) -> int | None:
        """The real image under ``light`` whose camera is nearest to ``view``'s in direction (``None``: none)."""
        candidates = self.real_of_light.get(light, [])
        if not candidates:
            return None
        views = torch.tensor([self.real.observations[i].view for i in candidates])
        similarity = self.view_dirs[views] @ self.view_dirs[view]
        return candidates[int(torch.argmax(similarity))]

    def surface_depth(self, view: int) -> Tensor:
        """The render's camera z at real view ``view`` (its own size) where it has a surface, else 0:
        ``[1, H, W]``."""
        if view not in self._depth:
            g = render_lattice_image(self.scene, self.real, view, 0).gbuffer
            self._depth[view] = torch.where(g.alpha[0, ..., 0] >= SURFACE_ALPHA, g.depth[0, ..., 0], 0.0)[None].cpu()
        return self._depth[view]

    def warped(self, view: int, light: int) -> Tensor:
        """The nearest real image under ``light`` warped into ``view``: sRGB (3) and validity (1), ``[4, H, W]``."""
        w2c, K, width, height = self.camera(view)
        index = self.source(view, light)
        if index is None:
            return torch.zeros(4, height, width)
        sample = self.real.load(index)
        source = self.real.cameras[sample.view]
        reference = linear_to_srgb(sample.rgb.clamp(0, 1)).permute(2, 0, 1)
        size = max(width, height)  # pixel intrinsics: a square canvas cropped to the image
        image, valid = forward_warp(reference, self.surface_depth(sample.view), source.w2c, source.K, w2c[None],
                                    K[None], size)
        return torch.cat([image[0], valid[0]])[:, :height, :width].float()

    def camera(self, view: int) -> tuple[Tensor, Tensor, int, int]:
        """``w2c``, ``K``, width and height of lattice view ``view`` at the model's size."""
        camera = self.lattice.cameras[view].resized(self.scale(view))
        return camera.w2c, camera.K, camera.width, camera.height

    def target(self, view: int, light: int) -> tuple[Tensor, SceneRender]:
        """The model's input ``[23, H, W]`` at lattice view ``view`` under lattice light ``light``, and the render
        it starts from."""
        (w2c, K, width, height), lit = self.camera(view), self.lattice.lights[light]
        render = self.render(view, light)
        device = render.radiance.device
        channels = render_channels(render, w2c.to(device), K.to(device), lit.position, self.near, self.far).cpu()
        code = light_code(lit.position, w2c, self.center, self.radius).float()
        constant = code[:, None, None].expand(-1, height, width)
        return torch.cat([channels, self.warped(view, light), constant]), render
