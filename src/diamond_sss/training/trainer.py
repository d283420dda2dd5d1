"""The SSS-3DGS / DIAMOND-SSS reconstruction loop.

One step: draw ``B`` (view, light) images (a pure function of the step, so resumed runs see the same
batches), render them with deferred shading at the first source's size, add the objective's terms (photometric,
regularisers, ray-traced visibility every ``raytrace_every`` steps, multi-view consistency), back-propagate, step Adam,
and let gsplat's ``DefaultStrategy`` densify and prune under ``gaussians.max_count`` (:class:`CappedStrategy`;
or keep the Gaussian count fixed), resetting the opacities every ``reset_every`` steps while it densifies
(:func:`opacity_reset_due`). With
``schedule.average_last`` the saved model is the mean of the scene tensors over the run's last steps
(:mod:`diamond_sss.training.averaging`).
An image smaller than the first source's (a generated image at its diffusion model's resolution) is compared
with the render area-downsampled to its size (:func:`area_downsample_render`, :meth:`Trainer.image_terms`): the
batch is rendered once, at full size, so densification and the multi-view terms see one render of every image.
Every random draw of step ``t`` comes from the streams of :mod:`diamond_sss.utils.rng` seeded with
``(seed, t)``: host streams for decisions taken in Python, device streams for tensors on the training device.
The step never waits for the device: the loss terms stay there (:class:`LossLog`) and are read, and checked
for non-finite values, once every ``log_every`` steps and before every checkpoint.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path

import torch
from gsplat.strategy.ops import reset_opa
from torch import Tensor
from tqdm.auto import tqdm

from diamond_sss.data.conventions import camera_centers, linear_to_srgb, scale_intrinsics
from diamond_sss.data.dataset import OLATDataset, seeded_epoch_indices
from diamond_sss.data.images import resize_area
from diamond_sss.gaussians.init import initial_points
from diamond_sss.gaussians.model import GAUSSIAN_PARAMS, GaussianModel
from diamond_sss.losses.lpips import load_lpips
from diamond_sss.losses.multiview import (
    MultiViewConfig,
    multiview_losses_batched,
    sample_foreground_pixels,
    sample_view_pairs,
)
from diamond_sss.losses.regularizers import raytrace_visibility_loss
from diamond_sss.scene.io import read_scene, save_scene, scene_from_tensors, scene_tensors
from diamond_sss.scene.model import RelightableScene, SceneRender
from diamond_sss.shading.deferred import GBuffer, ShadingResult
from diamond_sss.shading.light_depth import CachedLights, LightMapCache
from diamond_sss.shading.raytrace import raytraced_visibility
from diamond_sss.shading.sh import visibility_from_sh
from diamond_sss.training.averaging import ParameterAverage, averaging_start
from diamond_sss.training.checkpoint import resume_checkpoint, save_checkpoint
from diamond_sss.training.config import TrainConfig
from diamond_sss.training.densify import CappedStrategy, opacity_reset_due
from diamond_sss.training.lattice import unify_lattices
from diamond_sss.training.loss_log import LossLog
from diamond_sss.training.objective import TargetBatch, image_objective
from diamond_sss.training.run_folder import check_resumable, finished_summary
from diamond_sss.training.schedules import exponential_lr, linear_warmup, step_decay
from diamond_sss.utils import rng
from diamond_sss.utils.compiling import compile_unavailable, compiled
from diamond_sss.utils.device import cpu_threads, resolve_device, to_device
from diamond_sss.utils.io import atomic_write_json

logger = logging.getLogger(__name__)

GAUSSIAN_LR_KEYS = {param.name: param.lr for param in GAUSSIAN_PARAMS if param.lr is not None}
"""Gaussian parameter -> the config field of its learning rate (the positions have their own schedule)."""


@dataclass
class ImageSource:
    """A data set whose images train the scene with a photometric weight (1 real, alpha synthetic), times an
    optional factor per image (``image_factors[i]`` for observation ``i``, e.g. a generated image's agreement)."""

    dataset: OLATDataset
    weight: float = 1.0
    image_factors: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        factors = self.image_factors
        if factors is not None and len(factors) != len(self.dataset):
            raise ValueError(f"image_factors: {len(factors)} factors for the {len(self.dataset)} images of "
                             f"{self.dataset.json_path}")
        if not (math.isfinite(self.weight) and self.weight >= 0.0) or (
                factors is not None and not all(math.isfinite(f) and f >= 0.0 for f in factors)):
            raise ValueError(f"{self.dataset.json_path}: image weights must be finite and >= 0")

    def weight_of(self, index: int) -> float:
        """The photometric weight of observation ``index``."""
        return self.weight * (1.0 if self.image_factors is None else self.image_factors[index])


@dataclass
class SizeGroup:
    """The images of a batch that are ``width x height``: their positions ``items [n]`` in the batch and their
    targets at that size (intrinsics scaled to it)."""

    items: Tensor
    width: int
    height: int
    target: TargetBatch


PREMULTIPLIED_SHADING = ("radiance", "pbr", "diffuse", "specular", "residual")
"""The :class:`ShadingResult` maps that are premultiplied by alpha (its ``points`` are not)."""


def _area(images: Tensor, height: int, width: int) -> Tensor:
    """Area-average resize of channels-last ``[B,H,W,C]`` images (block means for integer factors)."""
    chw = images.permute(0, 3, 1, 2)
    return torch.nn.functional.interpolate(chw, size=(height, width), mode="area").permute(0, 2, 3, 1)


def area_downsample_render(render: SceneRender, items: Tensor, height: int, width: int,
                           eps: float = 1e-6) -> SceneRender:
    """Images ``items`` of ``render`` area-averaged to ``height x width`` (a sensor of that size over the full render).

    With ``A`` the area average: premultiplied maps (shaded images, alpha) ``x' = A(x)``; alpha-normalised maps
    (G-buffer attributes, depth, surface points) ``a' = A(alpha a) / A(alpha)``, 0 where ``A(alpha) <= eps`` (as
    :meth:`GBuffer.from_features`); at the render's own size the images are only selected. The rasterizer's output
    is the full render's.
    """
    gbuffer = render.gbuffer
    if gbuffer.alpha.shape[1:3] == (height, width):
        return SceneRender(
            shading=ShadingResult(**{f.name: getattr(render.shading, f.name)[items] for f in fields(ShadingResult)}),
            gbuffer=GBuffer(**{f.name: getattr(gbuffer, f.name)[items] for f in fields(GBuffer)}),
            raster=render.raster)
    alpha = gbuffer.alpha[items]
    low_alpha = _area(alpha, height, width)
    covered = low_alpha > eps
    inverse = torch.where(covered, 1.0 / low_alpha.clamp_min(eps), torch.zeros_like(low_alpha))

    def normalised(values: Tensor) -> Tensor:
        return _area(values[items] * alpha, height, width) * inverse

    maps = {f.name: normalised(getattr(gbuffer, f.name)) for f in fields(GBuffer) if f.name != "alpha"}
    shading = {f.name: (_area(getattr(render.shading, f.name)[items], height, width)
                        if f.name in PREMULTIPLIED_SHADING else normalised(getattr(render.shading, f.name)))
               for f in fields(ShadingResult)}
    return SceneRender(shading=ShadingResult(**shading), gbuffer=GBuffer(**maps, alpha=low_alpha),
                       raster=render.raster)


@dataclass
class TrainResult:
    """What a finished run reports."""

    steps: int
    seconds: float
    num_gaussians: int
    final_loss: float
    history: list[dict] = field(default_factory=list)
    averaged_steps: int = 0


StepCallback = Callable[[int, RelightableScene, dict[str, Tensor]], bool | None]
"""Called by :meth:`Trainer.run` after every step with the number of steps done, the scene and the step's
loss terms and ``total`` (detached scalars on the device; reading one waits for the device). Returning
``True`` ends the run after that step; an exception raised in it (e.g. Optuna's ``TrialPruned``) ends the
run without writing the model."""


def gaussian_optimizers(optimizers: dict[str, torch.optim.Optimizer]) -> dict[str, torch.optim.Optimizer]:
    """The per-Gaussian-parameter optimisers (what gsplat's strategies edit when they densify or prune)."""
    return {name: optimizers[name] for name in ("means", *GAUSSIAN_LR_KEYS)}


def strided_quantile(values: Tensor, q: float, max_count: int = 1_000_000) -> float:
    """The ``q`` quantile of ``values [N]`` over every ``s``-th value, ``s = ceil(N / max_count)`` (all of them for
    ``N <= max_count``): an even subsample of every image's pixels within ``torch.quantile``'s size limit."""
    stride = max(1, math.ceil(values.numel() / max_count))
    return float(torch.quantile(values[::stride], q))


class Trainer:
    """Reconstructs a relightable scene from one or more image sources sharing a lattice of cameras/lights.

    Args:
        cfg: the resolved configuration.
        sources: image sources; the first is the real capture and defines the lattice and the render size; the
            others' images may be smaller (each is compared at its own size, see :meth:`image_terms`).
        run_dir: output folder (checkpoints, TensorBoard, model, config); ``None``: write nothing.
        show_progress: show a tqdm bar.
    """

    def __init__(self, cfg: TrainConfig, sources: list[ImageSource], run_dir: Path | None,
                 show_progress: bool = True) -> None:
        if not sources or len(sources[0].dataset) == 0:
            raise ValueError("training needs at least one image")
        self.cfg = cfg
        self.sources = sources
        self.lattice = sources[0].dataset
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.show_progress = show_progress
        self.device = resolve_device(cfg.runtime.device)
        if (why := compile_unavailable(cfg.runtime.compile, self.device)) is not None:
            raise ValueError(f"config key 'runtime.compile' is '{cfg.runtime.compile}' but {why}: set compile=off "
                             "(eager, the default)")
        self.index = [(s, i) for s, source in enumerate(sources) for i in range(len(source.dataset))]
        self.bounds = self.lattice.bounds
        self.union = unify_lattices([source.dataset for source in sources])
        self.viewmats = self.union.viewmats.to(self.device)
        self.Ks = self.union.Ks.to(self.device)
        self.light_positions = self.union.light_positions.to(self.device)
        self.light_intensities = self.union.light_intensities.to(self.device)
        self.camera_centers = camera_centers(self.union.viewmats)
        self.width, self.height = self.union.width, self.union.height
        self.view_silhouettes = self._view_silhouettes()
        self._target_silhouettes: dict[int, Tensor] = {}
        self.loss_log = LossLog()
        self.lpips = load_lpips(cfg.runtime.lpips_weights or None) if cfg.losses.lambda_lpips > 0 else None
        self._objective = compiled(image_objective, cfg.runtime.compile)
        self._multiview_losses = compiled(multiview_losses_batched, cfg.runtime.compile)
        if self.lpips is not None:
            self.lpips = self.lpips.to(self.device)
        mv = cfg.multiview
        self.mv_cfg = MultiViewConfig(
            pairs_per_step=mv.pairs_per_step, pixels_per_pair=mv.pixels_per_pair, target_mode=mv.target_mode,
            nearest_k=mv.nearest_k, sil_threshold=mv.sil_threshold, occlusion_tol=mv.occlusion_tol,
            charbonnier_eps=mv.charbonnier_eps if mv.charbonnier_eps > 0 else None, sil_tolerance=mv.sil_tolerance,
            depth_tolerance=mv.depth_tolerance,
        )
        self.strategy = (CappedStrategy(**cfg.densify.strategy_kwargs(), max_count=cfg.gaussians.max_count,
                                        verbose=False) if cfg.densify.enabled else None)
        every = cfg.shading.sss_light_depth_every
        self.light_maps = LightMapCache(every) if cfg.shading.sss_light_depth > 0 and every > 1 else None

    # ------------------------------------------------------------------ set-up
    def _view_silhouettes(self) -> dict[int, Tensor]:
        """Mask of every (unified) view that has an image in any source (light-independent), at the render size
        (a smaller image's area-resized up to it); real first."""
        masks: dict[int, Tensor] = {}
        for source, view_map in zip(self.sources, self.union.view_maps):
            for index, obs in enumerate(source.dataset.observations):
                if view_map[obs.view] not in masks:
                    mask = resize_area(source.dataset.load(index).mask, self.height, self.width)
                    masks[view_map[obs.view]] = mask[..., 0].to(self.device)
        return masks

    def build_scene(self) -> RelightableScene:
        """Initial Gaussians (points3d.ply, visual hull of the training masks, or random) and a fresh MLP."""
        cfg = self.cfg
        torch.manual_seed(cfg.schedule.seed)
        generator = torch.Generator().manual_seed(cfg.schedule.seed)
        views = sorted({obs.view for obs in self.lattice.observations})
        w2c, K = self.lattice.viewmats, self.lattice.intrinsics
        if cfg.gaussians.hull_masks == "all":
            views, w2c, K = sorted(self.view_silhouettes), self.union.viewmats, self.union.Ks
        use_ply = cfg.gaussians.init in ("auto", "ply")
        use_hull = cfg.gaussians.init in ("auto", "hull")
        ply = self.lattice.root / "points3d.ply"
        if cfg.gaussians.init == "ply" and not ply.is_file():
            raise ValueError(f"config init='ply' but {ply} does not exist")
        points = initial_points(
            num_points=cfg.gaussians.count, bounds_center=self.bounds.center, bounds_radius=self.bounds.radius,
            points3d_path=ply if use_ply else None,
            masks=torch.stack([self.view_silhouettes[v].cpu() for v in views]) if use_hull else None,
            w2c=w2c[views] if use_hull else None,
            K=K[views] if use_hull else None,
            generator=generator,
        )
        self.init_source = points.source
        model = GaussianModel.from_points(points.points, points.colors, points.normals, generator=generator)
        shading = cfg.shading
        light_init = self.calibrated_light_init() if shading.light_init_from_data else shading.light_init
        return RelightableScene(model, sss_width=shading.sss_width, sss_position_freqs=shading.sss_position_freqs,
                                light_init=light_init,
                                scene_center=self.bounds.center, scene_radius=self.bounds.radius,
                                mixed_precision=shading.mixed_precision,
                                light_falloff=shading.light_falloff,
                                sss_angular_inputs=shading.sss_angular_inputs,
                                sss_light_depth=shading.sss_light_depth,
                                sss_visibility_gradient=shading.sss_visibility_gradient).to(self.device)

    def calibrated_light_init(self, max_images: int = 64) -> float:
        """``log`` of a global light scale matched to the capture's units (Tab. 3's ``light_init`` = -1 is
        tied to SSS-3DGS's data): ``log(2 q99 / mean(I_light))``, ``q99`` the 99th percentile of the brightest
        channel over foreground pixels of up to ``max_images`` training images (:func:`strided_quantile`). At that
        scale the sigmoid residual ``R I`` can reach twice the brightest observed radiance from the first step.
        """
        dataset = self.sources[0].dataset
        count = min(max_images, len(dataset))
        picks = torch.linspace(0, len(dataset) - 1, count).round().long().tolist()
        values, intensities = [], []
        for index in picks:
            sample = dataset.load(index)
            values.append(sample.rgb.amax(dim=-1)[sample.mask[..., 0] > 0.5])
            intensities.append(dataset.light_intensities[sample.light].mean())
        foreground = torch.cat(values)
        if foreground.numel() == 0:
            return self.cfg.shading.light_init
        q99 = strided_quantile(foreground, 0.99)
        return float(torch.log(torch.tensor(2.0 * max(q99, 1e-4)) / torch.stack(intensities).mean().clamp_min(1e-8)))

    def build_optimizers(self, scene: RelightableScene) -> dict[str, torch.optim.Optimizer]:
        """One Adam per Gaussian parameter (the layout gsplat's strategies need), the MLP and the light."""
        cfg = self.cfg
        params = scene.gaussians.params
        fused = {"fused": True} if self.device.type == "cuda" else {}
        optimizers: dict[str, torch.optim.Optimizer] = {
            "means": torch.optim.Adam([params["means"]], lr=cfg.lr.position_init * self.bounds.radius,
                                      eps=1e-15, **fused),
        }
        for name, key in GAUSSIAN_LR_KEYS.items():
            optimizers[name] = torch.optim.Adam([params[name]], lr=getattr(cfg.lr, key), eps=1e-15, **fused)
        optimizers["mlp"] = torch.optim.Adam(scene.mlp.parameters(), lr=cfg.lr.sss, **fused)
        optimizers["light"] = torch.optim.Adam([scene.log_light_scale], lr=cfg.lr.light, **fused)
        return optimizers

    def set_learning_rates(self, optimizers: dict[str, torch.optim.Optimizer], step: int) -> None:
        cfg = self.cfg
        decay = step_decay(step, cfg.lr.decay_step, cfg.lr.decay_factor)
        rates = {name: getattr(cfg.lr, key) * decay for name, key in GAUSSIAN_LR_KEYS.items()}
        rates["means"] = self.bounds.radius * exponential_lr(
            step, cfg.lr.position_init, cfg.lr.position_final, cfg.lr.position_max_steps,
            cfg.lr.position_delay_steps, cfg.lr.position_delay_mult)
        rates["mlp"] = cfg.lr.sss * decay * linear_warmup(step, cfg.lr.sss_warmup_steps)
        rates["light"] = cfg.lr.light * decay
        for name, optimizer in optimizers.items():
            for group in optimizer.param_groups:
                group["lr"] = rates[name]

    # ------------------------------------------------------------------ one step
    def draw_batch(self, step: int) -> tuple[list[tuple[int, int]], TargetBatch, Tensor, Tensor]:
        """The step's images: (source, observation) pairs, targets, light positions and intensities.

        ``target`` holds every image at the render size (a smaller one area-resized up to it) and the cameras
        of the render; the image objective compares each image at its own size, by the groups of
        ``_batch_groups`` (:class:`SizeGroup`, one per image size, in order of first appearance). Also keeps the
        batch's views and its masks at the render size on the host (``_batch_views``, ``_batch_masks``) for the
        multi-view pixel sampling, and its lights (``_batch_lights``, indices in the union) for the light map cache.
        """
        cfg = self.cfg
        generator = rng.stream_generator(cfg.schedule.seed, step, 0)
        picks = [self.index[i] for i in seeded_epoch_indices(step, cfg.schedule.batch_size, len(self.index),
                                                             cfg.schedule.seed)]
        rgbs, masks, weights, views, lights, sizes = [], [], [], [], [], []
        for source_index, obs_index in picks:
            source = self.sources[source_index]
            sample = source.dataset.load(obs_index)
            rgbs.append(sample.rgb)
            masks.append(sample.mask)
            weights.append(source.weight_of(obs_index))
            views.append(self.union.view_maps[source_index][sample.view])
            lights.append(self.union.light_maps[source_index][sample.light])
            sizes.append(self.union.view_sizes[source_index][sample.view])
        rgb = to_device(torch.stack([resize_area(x, self.height, self.width) for x in rgbs]), self.device)
        host_masks = torch.stack([resize_area(m, self.height, self.width) for m in masks])
        mask = to_device(host_masks, self.device)
        background = (rng.rand(len(picks), 1, 1, 3, generator=generator, device=self.device)
                      if cfg.shading.random_background else None)
        views_t = to_device(torch.tensor(views), self.device)
        lights_t = to_device(torch.tensor(lights), self.device)
        target = TargetBatch(rgb=rgb, mask=mask, weights=to_device(torch.tensor(weights), self.device),
                             viewmats=self.viewmats[views_t], Ks=self.Ks[views_t], background=background)
        self._batch_views = views
        self._batch_lights = lights
        self._batch_masks = host_masks
        self._batch_groups = self._size_groups(target, rgbs, masks, sizes)
        return picks, target, self.light_positions[lights_t], self.light_intensities[lights_t]

    def _size_groups(self, target: TargetBatch, rgbs: list[Tensor], masks: list[Tensor],
                     sizes: list[tuple[int, int]]) -> list[SizeGroup]:
        """The batch's images grouped by size (``target`` itself for a batch of render-size images alone)."""
        if all(size == (self.width, self.height) for size in sizes):
            return [SizeGroup(torch.arange(len(sizes), device=self.device), self.width, self.height, target)]
        groups = []
        for width, height in dict.fromkeys(sizes):
            members = [b for b, size in enumerate(sizes) if size == (width, height)]
            items = to_device(torch.tensor(members), self.device)
            groups.append(SizeGroup(items, width, height, TargetBatch(
                rgb=to_device(torch.stack([rgbs[b] for b in members]), self.device),
                mask=to_device(torch.stack([masks[b] for b in members]), self.device),
                weights=target.weights[items], viewmats=target.viewmats[items],
                Ks=scale_intrinsics(target.Ks[items], width / self.width, height / self.height),
                background=None if target.background is None else target.background[items])))
        return groups

    def image_terms(self, render: SceneRender, target: TargetBatch) -> dict[str, Tensor]:
        """:func:`image_objective` of the batch drawn last, each image compared at its own size.

        A batch of render-size images alone: ``image_objective(render, target)``. Else, over the groups ``g`` of
        ``n_g`` images of one size (``_batch_groups``), each term is ``T = sum_g (n_g / B) T_g`` with ``T_g`` the term
        of the group's targets and the render area-downsampled to their size (:func:`area_downsample_render`):
        the per-image-weighted photometric and LPIPS terms are then exactly ``(1/B) sum_b w_b E_b``; the pixel means
        of the other terms weigh each image once whatever its size.
        """
        groups = self._batch_groups
        if len(groups) == 1 and groups[0].target is target:
            return self._objective(render, target, self.cfg, self.lpips)
        batch = target.rgb.shape[0]
        terms: dict[str, Tensor] = {}
        for group in groups:
            part = area_downsample_render(render, group.items, group.height, group.width)
            share = group.items.numel() / batch
            for name, value in self._objective(part, group.target, self.cfg, self.lpips).items():
                terms[name] = terms[name] + share * value if name in terms else share * value
        return terms

    def raytrace_term(self, scene: RelightableScene, light_positions: Tensor, step: int) -> Tensor:
        """Eq. A.7 on a random subset of Gaussians: towards the batch's lights and random directions."""
        cfg = self.cfg
        g = scene.gaussians
        generator = rng.stream_generator(cfg.schedule.seed, step, 1, self.device)
        count = min(cfg.raytrace.gaussians, g.num_gaussians)
        subset = rng.randperm(g.num_gaussians, generator=generator)[:count]
        with torch.no_grad():
            traced = raytraced_visibility(g.means.detach(), g.quats.detach(), g.scales.detach(),
                                          g.opacities.detach(), light_positions, num_samples=cfg.raytrace.directions,
                                          generator=generator, normals=g.normals.detach(), sources=subset)
        predicted = visibility_from_sh(g.visibility_sh[subset][:, None, :], traced.dirs)
        return cfg.losses.lambda_visibility * raytrace_visibility_loss(predicted, traced.visibility)

    def multiview_terms(self, scene: RelightableScene, render, target: TargetBatch,
                        step: int) -> dict[str, Tensor]:
        """Silhouette and depth consistency between batch views (sources) and nearby lattice views.

        Nothing (an empty dict) before ``multiview.start_fraction * schedule.iterations`` steps. A target view with
        no image has no silhouette: it is drawn for the depth term only (its own rendered alpha, detached, filters
        that term), and gives no silhouette correspondences. With ``multiview.source_gradient = centres`` the
        sources' depth is rendered again with the blending weights held (one more geometry pass over the batch
        views): the terms then move Gaussian centres only, not the opacities through which the silhouette term
        otherwise deepens the expected depth (issue 58).
        """
        cfg = self.cfg
        if step < cfg.multiview.start_fraction * cfg.schedule.iterations:
            return {}
        generator = rng.stream_generator(cfg.schedule.seed, step, 2)
        candidates = torch.arange(self.union.num_views) if cfg.multiview.include_unobserved_views else torch.tensor(
            sorted(self.view_silhouettes))
        pairs = sample_view_pairs(self.camera_centers, cfg.multiview.pairs_per_step, cfg.multiview.target_mode,
                                  cfg.multiview.nearest_k, generator, candidates, torch.tensor(self._batch_views))
        if pairs.numel() == 0:
            return {}
        sources, targets = pairs[:, 0].tolist(), pairs[:, 1].tolist()
        tgt = to_device(torch.tensor(targets), self.device)
        factor = cfg.multiview.target_downscale
        tgt_width, tgt_height = max(1, self.width // factor), max(1, self.height // factor)
        tgt_K = scale_intrinsics(self.Ks[tgt], tgt_width / self.width, tgt_height / self.height)
        geometry = scene.render_geometry(self.viewmats[tgt], tgt_K, tgt_width, tgt_height)
        tgt_depth, tgt_alpha = geometry.depth[..., 0], geometry.alpha[..., 0]
        silhouettes = torch.stack([
            self._target_silhouette(t, tgt_height, tgt_width) if t in self.view_silhouettes
            else tgt_alpha[p].detach()
            for p, t in enumerate(targets)
        ])
        src = to_device(torch.tensor(sources), self.device)
        uv_list = [sample_foreground_pixels(self._batch_masks[b, ..., 0], cfg.multiview.pixels_per_pair, generator)
                   for b in sources]
        count = max(1, max(uv.shape[0] for uv in uv_list))
        host_uv = torch.full((len(sources), count, 2), 0.5)
        host_valid = torch.zeros(len(sources), count, dtype=torch.bool)
        for p, pixels in enumerate(uv_list):
            host_uv[p, : pixels.shape[0]] = pixels
            host_valid[p, : pixels.shape[0]] = True
        uv, valid = to_device(host_uv, self.device), to_device(host_valid, self.device)
        depth = render.gbuffer.depth
        if cfg.multiview.source_gradient == "centres":
            depth = scene.render_geometry(target.viewmats, target.Ks, depth.shape[-2], depth.shape[-3],
                                          centres_only=True).depth
        src_depth = depth[src, ..., 0]
        terms = self._multiview_losses(
            src_depth, render.gbuffer.alpha[src, ..., 0], uv, target.viewmats[src],
            target.Ks[src], tgt_depth, tgt_alpha, silhouettes, self.viewmats[tgt], tgt_K,
            self.bounds.near, self.bounds.far, self.mv_cfg, src_uv_valid=valid,
            tgt_silhouette_valid=to_device(torch.tensor([t in self.view_silhouettes for t in targets]), self.device),
        )
        out = {}
        if cfg.losses.lambda_sil > 0:
            out["mv_silhouette"] = cfg.losses.lambda_sil * terms.silhouette
        if cfg.losses.lambda_depth > 0:
            out["mv_depth"] = cfg.losses.lambda_depth * terms.depth
        return out

    def _target_silhouette(self, view: int, height: int, width: int) -> Tensor:
        """The mask of ``view`` area-resized to the multi-view target resolution (computed once per view)."""
        cached = self._target_silhouettes.get(view)
        if cached is None or cached.shape != (height, width):
            cached = resize_area(self.view_silhouettes[view][..., None], height, width)[..., 0]
            self._target_silhouettes[view] = cached
        return cached

    def training_step(self, scene: RelightableScene, optimizers: dict[str, torch.optim.Optimizer],
                      strategy_state: dict, step: int) -> dict[str, Tensor]:
        """One optimisation step; returns the loss terms and their ``total`` (detached scalars on the device).

        Nothing here reads a value back from the device: :class:`LossLog` checks the terms later.
        """
        cfg = self.cfg
        torch.manual_seed(cfg.schedule.seed * 1_000_003 + step)
        if scene.compiled_with != cfg.runtime.compile:
            scene.compile_shading(cfg.runtime.compile)
            if cfg.runtime.compile != "off":
                logger.info("runtime.compile=%s: the first steps compile the render and the losses (~30 s on CUDA), "
                            "and once more when the Gaussian count first changes", cfg.runtime.compile)
        self.set_learning_rates(optimizers, step)
        _, target, light_pos, light_rgb = self.draw_batch(step)
        cached_lights = None
        if self.light_maps is not None:
            self.light_maps.start_step(step)
            cached_lights = CachedLights(self.light_maps, self._batch_lights)
        render = scene.render(target.viewmats, target.Ks, self.width, self.height, light_pos, light_rgb,
                              cached_lights=cached_lights)
        info = render.raster.info
        if self.strategy is not None:
            self.strategy.step_pre_backward(scene.gaussians.params, gaussian_optimizers(optimizers),
                                            strategy_state, step, info)
        terms = self.image_terms(render, target)
        if cfg.losses.lambda_visibility > 0 and step % cfg.raytrace.every == 0:
            terms["raytrace"] = self.raytrace_term(scene, light_pos, step)
        if cfg.losses.lambda_sil > 0 or cfg.losses.lambda_depth > 0:
            terms.update(self.multiview_terms(scene, render, target, step))
        total = torch.stack(list(terms.values())).sum()
        total.backward()
        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        if self.strategy is not None:
            self.strategy.step_post_backward(scene.gaussians.params, gaussian_optimizers(optimizers),
                                             strategy_state, step, info, packed=False)
        if self.strategy is not None and opacity_reset_due(step, cfg.densify):
            reset_opa(scene.gaussians.params, gaussian_optimizers(optimizers), strategy_state,
                      value=2.0 * cfg.densify.prune_opa)
        values = {k: v.detach() for k, v in terms.items()}
        values["total"] = total.detach()
        return values

    # ------------------------------------------------------------------ the loop
    def run(self, resume: bool = False, *, scene: RelightableScene | None = None,
            on_step: StepCallback | None = None) -> TrainResult:
        """Train for ``cfg.schedule.iterations`` steps (continuing from the newest checkpoint when ``resume``).

        ``scene``: start from this scene instead of :meth:`build_scene` (trained in place). ``on_step`` is
        called after every step (see :data:`StepCallback`); when it returns ``True`` the run ends there.
        Without a ``run_dir`` nothing is written (no config, logs, checkpoints or model). On the CPU it trains on
        ``runtime.cpu_threads`` threads, restored when it returns.
        """
        with cpu_threads(self.cfg.runtime.cpu_threads if self.device.type == "cpu" else 0):
            return self._run(resume, scene, on_step)

    def _run(self, resume: bool, scene: RelightableScene | None, on_step: StepCallback | None) -> TrainResult:
        cfg = self.cfg
        if resume and (scene is not None or self.run_dir is None):
            raise ValueError("Trainer.run: resuming needs a run_dir and no starting scene")
        earlier_run = self.run_dir is not None and (self.run_dir / "config.json").is_file()
        if self.run_dir is not None:
            if resume:
                check_resumable(self.run_dir, cfg)
                if (finished := finished_summary(self.run_dir, cfg.schedule.iterations)) is not None:
                    logger.info("%s: already trained for %d steps", self.run_dir, finished["steps"])
                    self.scene = read_scene(self.run_dir / "model.safetensors", cfg.shading, self.device)
                    return TrainResult(steps=finished["steps"], seconds=finished["seconds"],
                                       num_gaussians=finished["num_gaussians"], final_loss=finished["final_loss"],
                                       history=finished.get("history", []),
                                       averaged_steps=finished.get("averaged_steps", 0))
            self.run_dir.mkdir(parents=True, exist_ok=True)
            atomic_write_json(self.run_dir / "config.json", cfg.to_dict())
        scene, optimizers, strategy_state, start_step, history, elapsed, average = self._start(
            resume, scene, earlier_run)
        average_from = averaging_start(cfg.schedule.iterations, cfg.schedule.average_last,
                                       cfg.densify.refine_stop_iter if self.strategy is not None else 0)
        if average.count != max(start_step - average_from, 0):  # a resumed run given another length
            logger.warning("%s: the parameter average holds %d steps where this run's window (from step %d) "
                           "holds %d: it restarts at step %d", self.run_dir, average.count, average_from,
                           max(start_step - average_from, 0), start_step)
            average = ParameterAverage()
        if self.light_maps is not None:
            self.light_maps.clear()
        if self.strategy is not None:
            self.strategy.check_sanity(scene.gaussians.params, gaussian_optimizers(optimizers))
        self.scene = scene
        writer = None if self.run_dir is None else _summary_writer(self.run_dir / "tb")
        started = time.perf_counter() - elapsed
        values: dict[str, float] = {"total": float("nan")}
        done = start_step
        self.loss_log = LossLog()
        iterations = cfg.schedule.iterations
        bar = tqdm(range(start_step, iterations), initial=start_step, total=iterations,
                   disable=not self.show_progress, desc="train", dynamic_ncols=True)
        for step in bar:
            try:
                terms = self.training_step(scene, optimizers, strategy_state, step)
                self.loss_log.record(step, terms)
                if step >= average_from:
                    average.add(scene_tensors(scene))
            except Exception:
                self.loss_log.flush()  # a non-finite loss before the failure is the better diagnosis
                raise
            done = step + 1
            last = (on_step is not None and bool(on_step(done, scene, terms))) or done == iterations
            checkpoint_due = (self.run_dir is not None and done % cfg.runtime.checkpoint_every == 0 and not last)
            if done % cfg.runtime.log_every == 0 or last or checkpoint_due:
                values = self.loss_log.flush()
            if done % cfg.runtime.log_every == 0 or last:
                record = {"step": done, "gaussians": scene.gaussians.num_gaussians,
                          "light_scale": float(scene.light_scale.detach()), **values}
                history.append(record)
                bar.set_postfix(loss=f"{values['total']:.4f}", n=scene.gaussians.num_gaussians)
                if writer is not None:
                    for key, value in record.items():
                        if key != "step":
                            writer.add_scalar(f"train/{key}", value, done)
            if writer is not None and (done % cfg.runtime.image_log_every == 0 or last):
                self._log_images(writer, scene, done)
            if checkpoint_due:
                save_checkpoint(self.run_dir, done, scene_tensors(scene), optimizers, strategy_state,
                                {"init_source": self.init_source, "history": history,
                                 "seconds": time.perf_counter() - started, "averaged_steps": average.count},
                                average=average.mean, keep=cfg.runtime.keep_checkpoints)
                if self.light_maps is not None:  # a run resumed here starts with no light maps either
                    self.light_maps.clear()
            if last:
                break
        bar.close()
        if average.count:
            scene.load_state_dict(average.mean)
            logger.info("the model is the mean of the last %d steps' parameters", average.count)
        result = TrainResult(steps=done, seconds=time.perf_counter() - started,
                             num_gaussians=scene.gaussians.num_gaussians, final_loss=values["total"],
                             history=history, averaged_steps=average.count)
        if writer is not None:
            writer.close()
        if self.run_dir is not None:
            self._save_outputs(scene, result)
        return result

    def _start(self, resume: bool, scene: RelightableScene | None, earlier_run: bool) -> tuple:
        """The scene, optimisers, strategy state, first step, history, seconds already spent and parameter average.

        Resuming a folder that an earlier run left without a checkpoint says so (a new folder is silent).
        """
        found = resume_checkpoint(self.run_dir) if resume else None
        if resume and found is None and earlier_run:
            logger.warning("%s: --resume but no checkpoint in %s: training from step 0", self.run_dir,
                           self.run_dir / "checkpoints")
        if found is None:
            if scene is None:
                scene = self.build_scene()
            else:
                self.init_source = "given"
            return scene, self.build_optimizers(scene), self._initial_strategy_state(), 0, [], 0.0, ParameterAverage()
        checkpoint, loaded = found
        scene = scene_from_tensors(loaded.scene, self.cfg.shading).to(self.device)
        optimizers = self.build_optimizers(scene)
        for name, optimizer in optimizers.items():
            optimizer.load_state_dict(loaded.optimizers[name])
        strategy_state = self._initial_strategy_state()
        strategy_state.update({k: (v.to(self.device) if torch.is_tensor(v) else v)
                               for k, v in loaded.strategy.items()})
        logger.info("%s: resuming from step %d (%s)", self.run_dir, loaded.step, checkpoint)
        self.init_source = loaded.extra.get("init_source", "checkpoint")
        average = ParameterAverage({k: v.to(self.device) for k, v in loaded.average.items()} or None,
                                   int(loaded.extra.get("averaged_steps", 0)))
        return (scene, optimizers, strategy_state, loaded.step, loaded.extra.get("history", []),
                float(loaded.extra.get("seconds", 0.0)), average)

    def _save_outputs(self, scene: RelightableScene, result: TrainResult) -> None:
        """``model.safetensors`` and ``train_summary.json`` of a finished run."""
        save_scene(self.run_dir / "model.safetensors", scene)
        atomic_write_json(self.run_dir / "train_summary.json", {
            "steps": result.steps, "seconds": round(result.seconds, 3), "num_gaussians": result.num_gaussians,
            "final_loss": result.final_loss, "init_source": self.init_source, "device": str(self.device),
            "averaged_steps": result.averaged_steps,
            "images": {f"source_{i}": len(s.dataset) for i, s in enumerate(self.sources)},
            "history": result.history,
        })

    def _initial_strategy_state(self) -> dict:
        if self.strategy is None:
            return {}
        return self.strategy.initialize_state(scene_scale=self.bounds.radius)

    @torch.no_grad()
    def _log_images(self, writer, scene: RelightableScene, step: int) -> None:
        obs = self.lattice.observations[0]
        render = scene.render(self.viewmats[obs.view][None], self.Ks[obs.view][None], self.width, self.height,
                              self.light_positions[obs.light][None], self.light_intensities[obs.light][None])
        gt = self.lattice.load(0).rgb.to(self.device)
        panel = torch.cat([linear_to_srgb(gt), linear_to_srgb(render.radiance[0])], dim=1)
        writer.add_image("train/gt_render", panel.clamp(0, 1).cpu(), step, dataformats="HWC")


def _summary_writer(path: Path):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        logger.warning("tensorboard is not installed: no TensorBoard logs")
        return None
    return SummaryWriter(str(path))

