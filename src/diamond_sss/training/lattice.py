"""One lattice of cameras and lights for several image sources (real capture + generated images).

Generated images may reuse the capture's cameras and lights (relighting, novel views at lattice poses) or add
new cameras (novel views at new poses), and may be smaller than the capture's (made at a diffusion model's
resolution). A camera's intrinsics are compared in pixels of the first source's image size (``K`` of a
``w x h`` image scaled by ``W / w``, ``H / h``: a 64 px image of a camera is that camera), so cameras are the
same when their ``w2c`` and rescaled ``K`` agree within a tolerance, and lights when their positions and
intensities do; indices of the first source are kept.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from diamond_sss.data.conventions import scale_intrinsics
from diamond_sss.data.dataset import Camera, OLATDataset


@dataclass
class UnifiedLattice:
    """Cameras ``viewmats [V,4,4]``, ``Ks [V,3,3]`` (in pixels of ``width x height``, the first source's size),
    lights ``[L,3]``, each source's index maps and the image size ``(w, h)`` of each source's views."""

    viewmats: Tensor
    Ks: Tensor
    light_positions: Tensor
    light_intensities: Tensor
    view_maps: list[list[int]]
    light_maps: list[list[int]]
    width: int
    height: int
    view_sizes: list[list[tuple[int, int]]]

    @property
    def num_views(self) -> int:
        return self.viewmats.shape[0]


def _match(rows: list[Tensor], row: Tensor, atol: float) -> int:
    for index, existing in enumerate(rows):
        if torch.allclose(existing, row, atol=atol, rtol=0.0):
            return index
    rows.append(row)
    return len(rows) - 1


def intrinsics_at(camera: Camera, width: int, height: int) -> Tensor:
    """``camera.K`` for an image of ``width x height``: ``K`` scaled by ``width / w`` (row 0) and ``height / h``
    (row 1); ``K`` itself when the camera is of that size."""
    if (camera.width, camera.height) == (width, height):
        return camera.K
    return scale_intrinsics(camera.K, width / camera.width, height / camera.height)


def _check_sizes(dataset: OLATDataset, width: int, height: int, capture: OLATDataset) -> None:
    """A ``ValueError`` naming the first view of ``dataset`` whose images are larger than ``width x height``."""
    for view in sorted({obs.view for obs in dataset.observations}):
        camera = dataset.cameras[view]
        if camera.width > width or camera.height > height:
            raise ValueError(f"{dataset.json_path}: view {view}'s images are {camera.width}x{camera.height}, larger "
                             f"than the capture {capture.json_path}'s {width}x{height}: images are compared with "
                             "renders at the capture's size (area-downsampled to theirs), so none may be larger")


def unify_lattices(datasets: Sequence[OLATDataset], tolerance: float = 1e-4) -> UnifiedLattice:
    """Union of the datasets' cameras and lights; the first dataset's indices are kept (see module docstring).

    Images may be smaller than the first dataset's (``W x H``), not larger. ``tolerance`` is relative to the
    scene radius (positions) and absolute for rotations, intrinsics (pixels of ``W x H`` x 1e3) and intensities.
    """
    first = datasets[0]
    width, height = first.width, first.height
    scale = max(first.bounds.radius, 1e-6)
    cameras: list[Tensor] = []
    lights: list[Tensor] = []
    view_maps, light_maps, view_sizes = [], [], []
    for dataset in datasets:
        _check_sizes(dataset, width, height, first)
        view_maps.append([
            _match(cameras, torch.cat([c.w2c[:3, :3].reshape(-1), c.w2c[:3, 3] / scale,
                                       intrinsics_at(c, width, height).reshape(-1) / 1e3]), tolerance)
            for c in dataset.cameras
        ])
        light_maps.append([
            _match(lights, torch.cat([light.position / scale, light.intensity]), tolerance)
            for light in dataset.lights
        ])
        view_sizes.append([(c.width, c.height) for c in dataset.cameras])
    viewmats = torch.zeros(len(cameras), 4, 4)
    Ks = torch.zeros(len(cameras), 3, 3)
    for dataset, view_map in zip(datasets, view_maps):
        for local, global_index in enumerate(view_map):
            viewmats[global_index] = dataset.cameras[local].w2c
            Ks[global_index] = intrinsics_at(dataset.cameras[local], width, height)
    positions = torch.zeros(len(lights), 3)
    intensities = torch.zeros(len(lights), 3)
    for dataset, light_map in zip(datasets, light_maps):
        for local, global_index in enumerate(light_map):
            positions[global_index] = dataset.lights[local].position
            intensities[global_index] = dataset.lights[local].intensity
    return UnifiedLattice(viewmats=viewmats, Ks=Ks, light_positions=positions, light_intensities=intensities,
                          view_maps=view_maps, light_maps=light_maps, width=width, height=height,
                          view_sizes=view_sizes)
