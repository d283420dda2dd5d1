"""Fine-tuning samples ``(source image, depth, normals, target light, target image)`` with the view fixed.

Taken from the embedded fine-tuning objects (``finetune/<object>``): every view that has at least
``min_lights`` lit images gives all ordered (source, target) light pairs, drawn uniformly over all pairs.
The images used are recorded and must stay within ``max_fraction`` (7%) of a full capture (views x lights of
the object's light stage).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.embedded import embedded_dataset, finetune_object_names
from diamond_sss.data.errors import DataError
from diamond_sss.diffusion.geometry.base import depth_to_nearness, world_to_camera_normals
from diamond_sss.diffusion.relight.conditioning import conditioning_image, image_to_model
from diamond_sss.diffusion.relight.light import light_code

MAX_FRACTION = 0.07


@dataclass
class RelightViews:
    """Per-view tensors at the model resolution: ``V`` views, view ``v`` seen under ``light_counts[v]`` lights
    (padded to ``L``, the largest count, by repeating its last image; padding is never drawn).

    Attributes:
        maps: conditioning maps without the source image ``[V,5,R,R]`` (nearness, normals, mask).
        images: target images in model space ``[V,L,3,R,R]``.
        sources: the same images as linear radiance ``[V,L,R,R,3]`` (to build source conditioning).
        codes: light codes ``[V,L,10]`` in each view's camera frame.
        light_counts: lights of each view ``[V]`` (int64, >= 2).
        selection: the recorded images (object, view, light, path) and the fraction of a capture used.
    """

    maps: Tensor
    images: Tensor
    sources: Tensor
    codes: Tensor
    light_counts: Tensor
    selection: dict

    @property
    def num_views(self) -> int:
        return self.images.shape[0]

    def batch(self, view: Tensor, source: Tensor, target: Tensor) -> dict[str, Tensor]:
        """Training batch for index tensors ``[B]``: conditioning ``[B,8,R,R]``, target, codes."""
        maps = self.maps[view]
        cond_source = image_to_model(self.sources[view, source])
        return {
            "conditioning": torch.cat([cond_source, maps], dim=1),
            "target": self.images[view, target],
            "source": self.images[view, source],
            "target_code": self.codes[view, target],
            "source_code": self.codes[view, source],
            "maps": maps,
        }

    def random_indices(self, batch_size: int, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
        """(view, source light, target light != source light) triples, uniform over all such pairs."""
        counts = self.light_counts.cpu()
        pairs = (counts * (counts - 1)).double()
        view = torch.multinomial(pairs, batch_size, replacement=True, generator=generator)
        count = counts[view]
        source = (torch.rand(batch_size, generator=generator) * count).long()
        shift = 1 + (torch.rand(batch_size, generator=generator) * (count - 1)).long()
        return view, source, (source + shift) % count


def view_maps(dataset: OLATDataset, view: int, mask: Tensor, resolution: int) -> Tensor:
    """Stored depth/normal maps of ``view`` as the 5 non-image conditioning channels ``[5,R,R]``."""
    depth, normals = dataset.load_geometry_maps(view)
    nearness = depth_to_nearness(depth[None], mask[None])
    normals_cam = world_to_camera_normals(normals[None], dataset.viewmats[view][None])
    cond = conditioning_image(torch.zeros_like(normals_cam), nearness, normals_cam, mask[None], resolution)
    return cond[0, 3:]


def _lit_views(dataset: OLATDataset, min_lights: int) -> dict[int, list[int]]:
    """Observation indices of each view with ``>= min_lights`` images and stored geometry maps."""
    by_view: dict[int, list[int]] = {}
    for index, obs in enumerate(dataset.observations):
        by_view.setdefault(obs.view, []).append(index)
    return {v: ix for v, ix in by_view.items() if len(ix) >= min_lights and dataset.has_geometry_maps(v)}


def _pad_lights(per_light: Tensor, count: int) -> Tensor:
    """``[n,...]`` -> ``[count,...]`` by repeating the last entry."""
    return torch.cat([per_light, per_light[-1:].expand(count - len(per_light), *per_light.shape[1:])])


def load_relight_views(
    roots: list[str | Path], resolution: int, min_lights: int = 2, max_fraction: float = MAX_FRACTION
) -> RelightViews:
    """Collect every view with ``>= min_lights`` images (and all its images) from the data folders ``roots``.

    Raises ``DataError`` when nothing usable is found or the selection exceeds ``max_fraction``.
    """
    if min_lights < 2:
        raise ValueError(f"min_lights must be >= 2 (a pair needs two lights), got {min_lights}")
    datasets = [OLATDataset(root, "train") for root in roots]
    lit_views = [_lit_views(dataset, min_lights) for dataset in datasets]
    counts = [len(indices) for views in lit_views for indices in views.values()]
    if not counts:
        raise DataError(
            f"no view with >= {min_lights} lights and depth/normal maps in {[str(r) for r in roots]}"
        )
    most = max(counts)
    maps, images, sources, codes, light_counts, records = [], [], [], [], [], []
    fractions = {}
    for root, dataset, views in zip(roots, datasets, lit_views):
        used = 0
        for view, indices in sorted(views.items()):
            rgb, mask = dataset.load_batch(indices)
            lights = torch.tensor([dataset.observations[i].light for i in indices])
            maps.append(view_maps(dataset, view, mask.amax(dim=0), resolution))
            linear = F.interpolate(rgb.permute(0, 3, 1, 2), size=(resolution, resolution), mode="area")
            linear = linear.permute(0, 2, 3, 1).contiguous()
            bounds = dataset.bounds
            w2c = dataset.viewmats[view].expand(len(indices), 4, 4)
            code = light_code(dataset.light_positions[lights], w2c, bounds.center, bounds.radius)
            sources.append(_pad_lights(linear, most))
            images.append(_pad_lights(image_to_model(linear), most))
            codes.append(_pad_lights(code, most))
            light_counts.append(len(indices))
            used += len(indices)
            records += [
                {
                    "object": Path(root).name,
                    "view": view,
                    "light": int(light),
                    "image": str(dataset.observations[i].image_path),
                }
                for i, light in zip(indices, lights)
            ]
        full = _full_capture_size(Path(root), dataset)
        fractions[Path(root).name] = used / full
        if used / full > max_fraction:
            raise DataError(
                f"{root}: fine-tuning would use {used} of {full} images ({used / full:.1%}), "
                f"more than {max_fraction:.0%} of a capture"
            )
    return RelightViews(
        maps=torch.stack(maps),
        images=torch.stack(images),
        sources=torch.stack(sources),
        codes=torch.stack(codes),
        light_counts=torch.tensor(light_counts, dtype=torch.int64),
        selection={"images": records, "fraction_of_capture": fractions, "max_fraction": max_fraction},
    )


def load_finetune_views(resolution: int) -> RelightViews:
    """:func:`load_relight_views` over all embedded fine-tuning objects."""
    names = finetune_object_names()
    if not names:
        raise DataError("no embedded fine-tuning objects (finetune/<object>) are installed")
    return load_relight_views([embedded_dataset(n) for n in names], resolution)


def _full_capture_size(root: Path, dataset: OLATDataset) -> int:
    """Views x lights of the full light stage (``meta.json``'s stage), else of the dataset's lattice."""
    meta = root / "meta.json"
    if meta.is_file():
        stage = json.loads(meta.read_text()).get("stage", {})
        if "views" in stage and "lights" in stage:
            return int(stage["views"]) * int(stage["lights"])
    return dataset.num_views * dataset.num_lights
