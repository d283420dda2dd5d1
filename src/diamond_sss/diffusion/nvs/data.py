"""Fixed-illumination multi-view sequences for fine-tuning the novel-view model.

A *sequence* is one light of one OLAT capture together with every view captured under it. A training
sample draws a reference view and ``V`` target views from one sequence, so the model learns geometry
without entangling lighting (supplement Sec. C.2). With ``with_depth`` every view also carries its stored
metric depth map (min-pooled to the image size), which the warp hint needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data import OLATDataset
from diamond_sss.data.conventions import scale_intrinsics
from diamond_sss.diffusion.nvs.model import NVSBatch
from diamond_sss.diffusion.nvs.warp import resize_depth


@dataclass
class Sequence:
    """Views of one object under one light: ``images [N,4,S,S]`` RGBA, ``w2c [N,4,4]``, ``K [N,3,3]``.

    ``depth [N,1,S,S]``: camera z of every view (0 = background), or None when not loaded.
    """

    name: str
    light: int
    views: list[int]
    images: Tensor
    w2c: Tensor
    K: Tensor
    depth: Tensor | None = None


def load_rgba_views(dataset: OLATDataset, views: list[int], light: int, size: int) -> tuple[Tensor, Tensor]:
    """RGBA images ``[N,4,size,size]`` (premultiplied linear colour, alpha) and their scaled intrinsics."""
    if dataset.width != dataset.height:
        raise ValueError(
            f"{dataset.root}: the novel-view model needs square images, got {dataset.width}x{dataset.height}"
        )
    rgb, mask = dataset.load_batch([dataset.observation_index(v, light) for v in views])
    rgba = torch.cat([rgb, mask], dim=-1).permute(0, 3, 1, 2).float()
    if rgba.shape[-1] != size:
        rgba = F.interpolate(rgba, size=(size, size), mode="area")
    K = scale_intrinsics(dataset.intrinsics[views], size / dataset.width)
    return rgba.clamp(0, 1), K


def load_depth_views(dataset: OLATDataset, views: list[int], size: int) -> Tensor:
    """Stored camera-z maps ``[N,1,size,size]`` of ``views`` (0 = background), min-pooled to ``size``."""
    missing = [v for v in views if not dataset.has_geometry_maps(v)]
    if missing:
        raise ValueError(
            f"{dataset.json_path}: views {missing} have no stored depth maps ('depth_path'); the warp hint "
            "needs metric depth (render the data with maps, or train with warp_hint=False)"
        )
    depth = torch.stack([dataset.load_geometry_maps(v)[0].permute(2, 0, 1) for v in views])
    return resize_depth(depth.float(), size)


def fixed_light_sequences(
    roots: list[str | Path], size: int, min_views: int = 2, with_depth: bool = False
) -> list[Sequence]:
    """Every (object, light) with at least ``min_views`` views, images (and depth maps) resized to ``size``."""
    sequences: list[Sequence] = []
    for root in roots:
        dataset = OLATDataset(root, "train")
        depth = None
        if with_depth:
            depth = load_depth_views(dataset, list(range(dataset.num_views)), size)
        for light in range(dataset.num_lights):
            views = [int(v) for v in torch.nonzero(dataset.presence[:, light]).flatten()]
            if len(views) < min_views:
                continue
            images, K = load_rgba_views(dataset, views, light, size)
            sequences.append(
                Sequence(
                    Path(root).name,
                    light,
                    views,
                    images,
                    dataset.viewmats[views].float(),
                    K,
                    None if depth is None else depth[views],
                )
            )
    if not sequences:
        raise ValueError(f"no light with >= {min_views} views in {[str(r) for r in roots]}")
    return sequences


def sample_batch(
    sequences: list[Sequence], num_objects: int, views_per_object: int, generator: torch.Generator
) -> NVSBatch:
    """``num_objects`` sequences (distinct objects first), a reference and ``views_per_object`` targets each.

    Targets are drawn among the sequence's other views, with repetition only when there are too few. The
    reference's depth map is included when the sequences carry depth.
    """
    names = sorted({s.name for s in sequences})
    object_order = torch.randperm(len(names), generator=generator).tolist()
    refs, ref_w2c, ref_K, ref_depth, tgts, tgt_w2c, tgt_K = [], [], [], [], [], [], []
    for i in range(num_objects):
        name = names[object_order[i % len(names)]]
        candidates = [s for s in sequences if s.name == name]
        seq = candidates[int(torch.randint(len(candidates), (1,), generator=generator))]
        n = len(seq.views)
        ref = int(torch.randint(n, (1,), generator=generator))
        others = torch.tensor([j for j in range(n) if j != ref])
        if len(others) >= views_per_object:
            pick = others[torch.randperm(len(others), generator=generator)[:views_per_object]]
        else:
            pick = others[torch.randint(len(others), (views_per_object,), generator=generator)]
        refs.append(seq.images[ref])
        ref_w2c.append(seq.w2c[ref])
        ref_K.append(seq.K[ref])
        if seq.depth is not None:
            ref_depth.append(seq.depth[ref])
        tgts.append(seq.images[pick])
        tgt_w2c.append(seq.w2c[pick])
        tgt_K.append(seq.K[pick])
    return NVSBatch(
        reference=torch.stack(refs),
        reference_w2c=torch.stack(ref_w2c),
        target_w2c=torch.stack(tgt_w2c),
        target_K=torch.stack(tgt_K),
        targets=torch.stack(tgts),
        reference_K=torch.stack(ref_K),
        reference_depth=torch.stack(ref_depth) if len(ref_depth) == num_objects else None,
    )
