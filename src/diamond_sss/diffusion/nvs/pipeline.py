"""Novel-view generation: the in-memory pipeline, and for an OLAT data set reference (view, light) -> target
cameras, cached.

Outputs in ``out``: ``images/<name>.png``, ``masks/<name>.png`` and ``manifest.json``
(:mod:`~diamond_sss.diffusion.common.manifest`; ``<name>`` is ``view_<index>`` for a lattice view or
``pose_<index>`` for a camera read from a pose file, listed with view ``None``). Generation is cached under a key of
the model hash and the hash of every input (reference image and mask, cameras, settings, and the geometry source that
gives a warp-hint model the reference's metric depth).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data import OLATDataset
from diamond_sss.data.conventions import (
    intrinsics_from_fov,
    mean_up_vector,
    opengl_c2w_to_opencv_w2c,
    scale_intrinsics,
)
from diamond_sss.data.images import reframe, to_srgb8, write_png
from diamond_sss.diffusion.common.cache import OutputCache
from diamond_sss.diffusion.common.hashing import files_hash
from diamond_sss.diffusion.common.manifest import GeneratedImage, image_paths, write_image_manifest
from diamond_sss.diffusion.common.paths import default_cache_dir, shipped_model_dir
from diamond_sss.diffusion.common.sampling import PipelineOutput, ddim_sample
from diamond_sss.diffusion.common.schedulers import make_ddim_scheduler
from diamond_sss.diffusion.geometry.base import GeometryError, GeometrySource
from diamond_sss.diffusion.nvs.canonical import canonical_frame
from diamond_sss.diffusion.nvs.data import load_rgba_views
from diamond_sss.diffusion.nvs.model import (
    NVSBatch,
    NVSConfig,
    NVSModel,
    hint_base,
    shared_noise,
)
from diamond_sss.diffusion.nvs.warp import forward_warp, resize_depth
from diamond_sss.utils.io import sha256_file


def default_model_dir() -> Path:
    """The novel-view model shipped inside the package (:func:`~diamond_sss.diffusion.common.paths.shipped_model_dir`)."""
    return shipped_model_dir("nvs")


class NovelViewPipeline:
    """In-memory novel-view generation: an :class:`NVSModel` sampled with DDIM (``eta = 0``) and
    classifier-free guidance ``eps = eps_u + s (eps_c - eps_u)``, whose unconditional branch drops image,
    reference, rays and warp hint. One initial noise per object, shared by its views."""

    def __init__(self, model: NVSModel) -> None:
        self.model = model

    @torch.no_grad()
    def __call__(
        self,
        batch: NVSBatch,
        num_steps: int = 50,
        guidance_scale: float = 3.0,
        generator: torch.Generator | None = None,
        size: int | None = None,
    ) -> PipelineOutput:
        """The target views of ``batch``, ``B*V`` images (views of an object contiguous) at the model's image
        size, or bilinearly resized to ``size``."""
        model, config = self.model, self.model.config
        batch.validate()
        b, v = batch.target_w2c.shape[:2]
        device = batch.reference.device
        reference = model.encode(batch.reference)
        hint = model.warp_hint(batch)
        base = hint_base(hint) if config.hint_residual else 0.0
        rays, pose = model.conditioning(batch, reference)
        embedding = model.reference_encoder(reference).repeat_interleave(v, dim=0)
        ref = reference.repeat_interleave(v, dim=0)
        keep = torch.zeros(b * v, dtype=torch.bool, device=device)
        cond = model.context(embedding, pose, keep)
        guided = guidance_scale != 1.0
        if guided:
            cond = torch.cat([cond, model.context(embedding, pose, ~keep)])
            ref = torch.cat([ref, torch.zeros_like(ref)])
            rays = torch.cat([rays, torch.zeros_like(rays)])
            if hint is not None:
                hint = torch.cat([hint, torch.zeros_like(hint)])

        def denoise(x: Tensor, timesteps: Tensor) -> Tensor:
            pred = model.denoise(torch.cat([x, x]) if guided else x,
                                 torch.cat([timesteps, timesteps]) if guided else timesteps, ref, cond, rays, v, hint)
            if not guided:
                return pred
            pred_c, pred_u = pred.chunk(2)
            return pred_u + guidance_scale * (pred_c - pred_u)

        shape = (config.model_channels, config.model_size, config.model_size)
        noise = shared_noise(b, v, shape, generator=generator, device=device).flatten(0, 1)
        scheduler = make_ddim_scheduler(config.scheduler, config.sample_clip_range)
        x = ddim_sample(denoise, (b * v, *shape), scheduler, num_steps, device=device, noise=noise)
        rgba = model.decode(x + base).float().cpu()
        if size is not None:
            rgba = F.interpolate(rgba, size=(size, size), mode="bilinear", align_corners=False).clamp(0, 1)
        return PipelineOutput(rgb=rgba[:, :3].permute(0, 2, 3, 1), alpha=rgba[:, 3:].permute(0, 2, 3, 1))


@dataclass
class TargetCameras:
    """Cameras to generate: ``w2c [T,4,4]`` OpenCV, ``K [T,3,3]`` at ``size`` pixels, and their labels: the
    lattice view of each (``None`` for a camera given by its pose, off the lattice) and its file name."""

    w2c: Tensor
    K: Tensor
    views: list[int | None]
    names: list[str]
    size: int

    @classmethod
    def from_views(cls, dataset: OLATDataset, views: Sequence[int]) -> TargetCameras:
        """The cameras of lattice views ``views`` of ``dataset`` (named ``view_<index>``)."""
        views = list(views)
        if not views:
            raise ValueError("no target view given")
        bad = [v for v in views if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < dataset.num_views]
        if bad:
            raise ValueError(
                f"unknown view index {bad} (the {dataset.split} split has views 0..{dataset.num_views - 1})"
            )
        return cls(
            dataset.viewmats[views].double(),
            dataset.intrinsics[views].double(),
            views,
            [f"view_{v:03d}" for v in views],
            dataset.width,
        )


def _matrix(value, shape: tuple[int, int], where: str) -> Tensor:
    try:
        matrix = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: expected a {shape[0]}x{shape[1]} matrix of numbers ({err})") from None
    if matrix.shape != shape or not torch.isfinite(matrix).all():
        raise ValueError(
            f"{where}: expected a finite {shape[0]}x{shape[1]} matrix, got shape {tuple(matrix.shape)}"
        )
    return matrix


def parse_targets(targets: str, dataset: OLATDataset) -> TargetCameras:
    """Target cameras from lattice view indices (``"3,7,12"``) or a JSON file of camera matrices.

    JSON: a list of 4x4 OpenGL camera-to-world matrices, or ``{"camera_angle_x": f, "frames":
    [{"transform_matrix": M}, ...]}`` as in ``transforms_*.json``; without a field of view the data set's
    intrinsics are used.
    """
    text = targets.strip()
    if _is_index_list(text):
        views = json.loads(text)
    elif text.endswith(".json") or text.startswith(("[", "{")):
        return _targets_from_json(text, dataset)
    else:
        try:
            views = [int(part) for part in text.replace(" ", "").split(",") if part]
        except ValueError:
            raise ValueError(
                f"--targets must be view indices like '3,7,12' or a JSON file of poses, got {targets!r}"
            ) from None
    if not views:
        raise ValueError("--targets lists no view")
    return TargetCameras.from_views(dataset, views)


def _is_index_list(text: str) -> bool:
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        return False
    return isinstance(value, list) and all(isinstance(v, int) for v in value)


def _targets_from_json(text: str, dataset: OLATDataset) -> TargetCameras:
    source = text
    if text.endswith(".json") and not text.startswith(("[", "{")):
        path = Path(text)
        if not path.is_file():
            raise ValueError(f"pose file {path} not found")
        text, source = path.read_text(), str(path)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"malformed pose JSON in {source}: {err}") from None
    if isinstance(data, list) and all(isinstance(v, int) for v in data):
        return TargetCameras.from_views(dataset, data)
    fov = None
    if isinstance(data, dict):
        if not isinstance(data.get("frames"), list):
            raise ValueError(f"pose JSON {source}: an object needs a 'frames' list")  # noqa: TRY004 (bad data)
        fov = data.get("camera_angle_x")
        try:
            matrices = [frame["transform_matrix"] for frame in data["frames"]]
        except (KeyError, TypeError):
            raise ValueError(f"pose JSON {source}: every frame needs a 'transform_matrix'") from None
    elif isinstance(data, list):
        matrices = data
    else:
        raise ValueError(f"pose JSON {source}: expected a list of 4x4 matrices or an object with 'frames'")  # noqa: TRY004
    if not matrices:
        raise ValueError(f"pose JSON {source} holds no camera")
    c2w = torch.stack([_matrix(m, (4, 4), f"pose JSON {source}, camera {i}") for i, m in enumerate(matrices)])
    w2c = opengl_c2w_to_opencv_w2c(c2w)
    size = dataset.width
    if fov is not None:
        K = intrinsics_from_fov(float(fov), size, size).double().expand(len(matrices), 3, 3)
    else:
        K = dataset.intrinsics[:1].double().expand(len(matrices), 3, 3)
    n = len(matrices)
    return TargetCameras(w2c, K.clone(), [None] * n, [f"pose_{i:03d}" for i in range(n)], size)


def reference_depth(
    dataset: OLATDataset, view: int, light: int, geometry: GeometrySource, size: int
) -> Tensor:
    """Metric camera z ``[1,1,size,size]`` (0 = background) of reference ``(view, light)`` from ``geometry``."""
    photo = dataset.load(dataset.observation_index(view, light))
    depth = geometry.maps(dataset, view, photo.rgb, photo.mask).depth
    if depth is None:
        raise GeometryError(
            f"geometry source '{geometry.key()['kind']}' gives only relative depth; the novel-view warp hint "
            "needs metric depth: use 'maps' (stored depth maps) or a reconstruction run folder"
        )
    return resize_depth(depth.permute(2, 0, 1)[None].float(), size)


def warp_reference_views(
    dataset: OLATDataset,
    view: int,
    light: int,
    cameras: TargetCameras,
    geometry: GeometrySource,
    config: NVSConfig,
) -> Tensor:
    """The warp hint as ``config``'s model sees it, RGBA ``[T,4,S,S]`` upsampled to the targets' size ``S``."""
    source = config.warp_source_size
    reference, ref_K = load_rgba_views(dataset, [view], light, source)
    depth = reference_depth(dataset, view, light, geometry, source)
    size = config.image_size
    warped, _ = forward_warp(
        reference[0],
        depth[0],
        dataset.viewmats[view].float(),
        ref_K[0].float(),
        cameras.w2c.float(),
        scale_intrinsics(cameras.K, size / cameras.size).float(),
        size,
    )
    return F.interpolate(warped, size=(cameras.size, cameras.size), mode="bilinear", align_corners=False)


def generate_novel_views(
    data: str | Path,
    out: str | Path,
    view: int,
    light: int,
    targets: Sequence[int] | TargetCameras,
    split: str = "train",
    model_dir: str | Path | None = None,
    steps: int = 1,
    guidance_scale: float = 1.0,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    device: str = "cpu",
    geometry: GeometrySource | None = None,
    downscale: float = 1.0,
    canonical: bool = False,
    model: NVSModel | None = None,
    reference_K: Tensor | None = None,
) -> Path:
    """Generate the ``targets`` (lattice view indices or cameras, see :func:`parse_targets`) of ``data`` under
    ``light`` from reference ``view``; returns the manifest (:mod:`~diamond_sss.diffusion.common.manifest`).

    A model with the warp hint needs ``geometry`` giving the reference's metric depth (stored maps or a
    reconstruction run folder). The images are written at the model's resolution (``image_size``), or at the
    targets' size when that is smaller (bilinear), never upsampled: the targets' size is that of ``data``'s images
    divided by ``downscale`` (``OLATDataset``'s), cameras given as :class:`TargetCameras` at their own ``size``.
    Deterministic for a seed, the same initial noise on every device (drawn on the CPU); a second call with the
    same model and inputs is served from the cache. ``canonical``: the cameras (and depth) are given to the prior in its own rig's frame
    (:mod:`~diamond_sss.diffusion.nvs.canonical`; from ``data``'s cameras), not in the capture's. ``model``: the model
    of ``model_dir`` already loaded on ``device`` (loaded here when not given; pass it when generating several times).
    ``reference_K``: intrinsics ``[3,3]`` at the capture's size over ``downscale`` in which the prior sees the
    reference view, its image, mask and depth resampled to them (:func:`~diamond_sss.data.images.reframe`; same pose;
    the pipeline's ``rig_framing=prior`` frames it as the priors' training cameras); None: as captured.
    """
    dataset = OLATDataset(data, split, downscale=downscale)
    if not 0 <= view < dataset.num_views:
        raise ValueError(
            f"unknown view index {view} (the {split} split has views 0..{dataset.num_views - 1})"
        )
    if not 0 <= light < dataset.num_lights:
        raise ValueError(
            f"unknown light index {light} (the {split} split has lights 0..{dataset.num_lights - 1})"
        )
    if not bool(dataset.presence[view, light]):
        raise ValueError(f"view {view} was not captured under light {light} in {dataset.json_path}")
    if isinstance(targets, str):
        raise TypeError(f"targets must be view indices or TargetCameras, got the string {targets!r} (parse_targets "
                        "reads the command line's form)")
    cameras = targets if isinstance(targets, TargetCameras) else TargetCameras.from_views(dataset, targets)
    model_dir = Path(model_dir) if model_dir is not None else default_model_dir()
    config = model.config if model is not None else NVSModel.read_config(model_dir)
    if config.warp_hint and geometry is None:
        raise GeometryError(
            f"the novel-view model in {model_dir} uses the warp hint and needs the reference's metric depth: "
            "pass a geometry source ('maps' or a reconstruction run folder)"
        )
    observation = dataset.observations[dataset.observation_index(view, light)]
    seen_K = dataset.intrinsics[view].double() if reference_K is None else reference_K.double().cpu()
    if seen_K.shape != (3, 3) or not bool(torch.isfinite(seen_K).all()) or min(float(seen_K[0, 0]),
                                                                                float(seen_K[1, 1])) <= 0:
        raise ValueError(f"reference_K must be a finite [3,3] matrix with positive focal lengths (view {view} of "
                         f"{dataset.json_path}), got {seen_K.tolist()}")
    frame = canonical_frame(dataset.viewmats, dataset.bounds.center, mean_up_vector(dataset.viewmats)) \
        if canonical else None
    output_size = min(cameras.size, config.image_size)
    key = OutputCache.key(
        {
            "model": files_hash(model_dir),
            "reference": sha256_file(observation.image_path),
            "reference_mask": None if observation.mask_path is None else sha256_file(observation.mask_path),
            "reference_w2c": dataset.viewmats[view].tolist(),
            "reference_K": dataset.intrinsics[view].tolist(),
            "targets_w2c": cameras.w2c.tolist(),
            "targets_K": cameras.K.tolist(),
            "size": cameras.size,
            "output_size": output_size,
            "names": cameras.names,
            "steps": steps,
            "guidance_scale": guidance_scale,
            "canonical_frame": None if frame is None else [frame.rotation.tolist(), frame.center.tolist(), frame.scale],
            "seed": seed,
            "geometry": geometry.view_key(dataset, view) if config.warp_hint else None,
            **({} if reference_K is None else {"reference_seen_K": seen_K.tolist()}),
        }
    )
    cache = OutputCache(cache_dir if cache_dir is not None else default_cache_dir("nvs"))

    def write(folder: Path) -> None:
        loaded = model if model is not None else NVSModel.load(model_dir).to(device)
        size = config.warp_source_size if config.warp_hint else config.image_size
        reference, ref_K = load_rgba_views(dataset, [view], light, size)
        depth = reference_depth(dataset, view, light, geometry, size) if config.warp_hint else None
        if reference_K is not None:  # the reference seen through other intrinsics (same pose)
            framed_K = scale_intrinsics(seen_K, size / dataset.width)[None].to(ref_K)
            reference = reframe(reference, ref_K, framed_K)
            depth = None if depth is None else reframe(depth, ref_K, framed_K, mode="nearest")
            ref_K = framed_K
        K = scale_intrinsics(cameras.K, size / cameras.size)
        reference_w2c, target_w2c = dataset.viewmats[view][None], cameras.w2c[None]
        if frame is not None:  # the prior's own rig (diffusion/nvs/canonical.py): metric depth scales with it
            reference_w2c, target_w2c = frame.w2c(reference_w2c), frame.w2c(target_w2c)
            depth = None if depth is None else depth * frame.scale
        batch = NVSBatch(
            reference=reference.to(device),
            reference_w2c=reference_w2c.float().to(device),
            target_w2c=target_w2c.float().to(device),
            target_K=K[None].float().to(device),
            reference_K=ref_K.float().to(device),
            reference_depth=None if depth is None else depth.to(device),
        )
        generator = torch.Generator().manual_seed(seed)  # on the CPU: the same noise on every device
        output = NovelViewPipeline(loaded)(batch, steps, guidance_scale, generator, size=output_size)
        for name, rgb, alpha in zip(cameras.names, output.rgb, output.alpha):
            write_png(folder / f"{name}.png", to_srgb8(rgb, alpha))
            write_png(folder / f"{name}_mask.png", (alpha[..., 0].numpy() * 255 + 0.5).astype("uint8"))

    entry, _ = cache.get_or_create(key, write)
    items = []
    for target_view, name in zip(cameras.views, cameras.names):
        item = GeneratedImage(target_view, light, *image_paths(out, name))
        for cached, path in ((f"{name}.png", item.image), (f"{name}_mask.png", item.mask)):
            path.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(entry / cached, path.with_name(f".{path.name}.tmp"))
            os.replace(path.with_name(f".{path.name}.tmp"), path)
        items.append(item)
    return write_image_manifest(out, items)
