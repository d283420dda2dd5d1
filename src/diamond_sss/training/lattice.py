"""One lattice of cameras and lights for several image sources (real capture + generated images).

Generated images may reuse the capture's cameras and lights (relighting, novel views at lattice poses) or add
new cameras (novel views at new poses). Cameras are the same when their ``w2c`` and ``K`` agree within a
tolerance and lights when their positions and intensities do; indices of the first source are kept.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from diamond_sss.data.dataset import OLATDataset


@dataclass
class UnifiedLattice:
    """Cameras ``viewmats [V,4,4]``, ``Ks [V,3,3]``, lights ``[L,3]`` and each source's index maps."""

    viewmats: Tensor
    Ks: Tensor
    light_positions: Tensor
    light_intensities: Tensor
    view_maps: list[list[int]]
    light_maps: list[list[int]]
    width: int
    height: int

    @property
    def num_views(self) -> int:
        return self.viewmats.shape[0]


def _match(rows: list[Tensor], row: Tensor, atol: float) -> int:
    for index, existing in enumerate(rows):
        if torch.allclose(existing, row, atol=atol, rtol=0.0):
            return index
    rows.append(row)
    return len(rows) - 1


def unify_lattices(datasets: Sequence[OLATDataset], tolerance: float = 1e-4) -> UnifiedLattice:
    """Union of the datasets' cameras and lights; the first dataset's indices are kept (see module docstring).

    All images must have the first dataset's size. ``tolerance`` is relative to the scene radius (positions)
    and absolute for rotations, intrinsics (pixels x 1e3) and intensities.
    """
    first = datasets[0]
    width, height = first.width, first.height
    scale = max(first.bounds.radius, 1e-6)
    cameras: list[Tensor] = []
    lights: list[Tensor] = []
    view_maps, light_maps = [], []
    for dataset in datasets:
        if (dataset.width, dataset.height) != (width, height):
            raise ValueError(f"{dataset.json_path}: images are {dataset.width}x{dataset.height}, but the capture "
                             f"{first.json_path} is {width}x{height}; generate images at the capture's size")
        view_maps.append([
            _match(cameras, torch.cat([c.w2c[:3, :3].reshape(-1), c.w2c[:3, 3] / scale, c.K.reshape(-1) / 1e3]),
                   tolerance)
            for c in dataset.cameras
        ])
        light_maps.append([
            _match(lights, torch.cat([light.position / scale, light.intensity]), tolerance)
            for light in dataset.lights
        ])
    viewmats = torch.zeros(len(cameras), 4, 4)
    Ks = torch.zeros(len(cameras), 3, 3)
    for dataset, view_map in zip(datasets, view_maps):
        for local, global_index in enumerate(view_map):
            viewmats[global_index] = dataset.cameras[local].w2c
            Ks[global_index] = dataset.cameras[local].K
    positions = torch.zeros(len(lights), 3)
    intensities = torch.zeros(len(lights), 3)
    for dataset, light_map in zip(datasets, light_maps):
        for local, global_index in enumerate(light_map):
            positions[global_index] = dataset.lights[local].position
            intensities[global_index] = dataset.lights[local].intensity
    return UnifiedLattice(viewmats=viewmats, Ks=Ks, light_positions=positions, light_intensities=intensities,
                          view_maps=view_maps, light_maps=light_maps, width=width, height=height)
