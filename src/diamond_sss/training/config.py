"""Training configuration: every hyperparameter of supplement Tab. 3 / Tab. 4 in nested groups, the presets.

A :class:`TrainConfig` holds one dataclass per concern (``schedule``, ``lr``, ``gaussians``, ``densify``,
``shading``, ``losses``, ``multiview``, ``raytrace``, ``runtime``). A key is written dotted
(``losses.lambda_dssim``) or by its flat name (``lambda_dssim``, the single-level layout of runs and tuning
studies made before the groups; every flat name is unique). Both are accepted everywhere a key is given.

Presets (:data:`PRESETS`, config instances):
    ``sss3dgs``  Tab. 4 "Original" (the SSS-3DGS release), no multi-view losses.
    ``diamond``  Tab. 3 / Tab. 4 "Best", with the multi-view silhouette (0.5) and depth (0.3) losses (also named
                 ``paper``).
The command line's default, :data:`AUTO_PRESET`, is no config instance: it depends on the run's length and capture
(``diamond`` with :func:`short_schedule`).

Values given as text or JSON are checked and applied by :mod:`diamond_sss.training.overrides`.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from diamond_sss.utils.fields import described


def _key(default: Any, meaning: str, flat: str | None = None) -> Any:
    """A config field with its meaning (``diamond-sss config`` and ``--set`` read it) and, where it differs
    from the field name, its ``flat`` name in the single-level layout of earlier runs."""
    return described(default, meaning, **({"flat": flat} if flat else {}))


@dataclass(frozen=True)
class Schedule:
    """Length of the run and its seed."""

    iterations: int = _key(10_000, "training steps")
    batch_size: int = _key(4, "images per training step")
    seed: int = _key(0, "seed of the regime selection, initialisation and every random draw")
    average_last: float = _key(0.0, "fraction of the run's last steps over which every scene tensor is averaged "
                               "(uniform mean, from densification's end at the earliest); the saved model is the "
                               "mean (0: the last step's parameters)")


@dataclass(frozen=True)
class LearningRates:
    """Learning rates per parameter group (Tab. 3); the Gaussian ones are named in ``GAUSSIAN_PARAMS``."""

    position_init: float = _key(0.00016, "initial learning rate of the means (times the scene radius)",
                                "position_lr_init")
    position_final: float = _key(0.0000016, "final learning rate of the means (exponential decay)",
                                 "position_lr_final")
    position_delay_mult: float = _key(0.01, "learning rate factor of the means at the start of the delay",
                                      "position_lr_delay_mult")
    position_delay_steps: int = _key(0, "steps of the means' learning rate warm-up delay",
                                     "position_lr_delay_steps")
    position_max_steps: int = _key(30_000, "step at which the means' learning rate reaches its final value",
                                   "position_lr_max_steps")
    normal: float = _key(0.01, "learning rate of the normals", "normal_lr")
    opacity: float = _key(0.05, "learning rate of the opacities", "opacity_lr")
    scaling: float = _key(0.005, "learning rate of the scales", "scaling_lr")
    rotation: float = _key(0.001, "learning rate of the rotations", "rotation_lr")
    base_color: float = _key(0.01, "learning rate of the base colours", "base_color_lr")
    roughness: float = _key(0.01, "learning rate of the roughness", "roughness_lr")
    metallic: float = _key(0.01, "learning rate of the metalness", "metallic_lr")
    subsurfacedness: float = _key(0.01, "learning rate of the subsurfaceness", "subsurfacedness_lr")
    visibility: float = _key(0.0025, "learning rate of the visibility SH coefficients", "visibility_lr")
    sss: float = _key(0.001, "learning rate of the subsurface-scattering MLP", "sss_lr")
    sss_warmup_steps: int = _key(0, "steps of a linear warm-up of the MLP's learning rate from 0",
                                 "sss_lr_warmup_steps")
    light: float = _key(0.001, "learning rate of the log light scale", "light_lr")
    decay_step: int = _key(50_000, "step from which every learning rate but the means' (which follow their own "
                           "exponential schedule) is multiplied by lr.decay_factor (once)", "lr_decay_step")
    decay_factor: float = _key(0.1, "factor on every learning rate but the means' from lr.decay_step on",
                               "lr_decay_factor")


@dataclass(frozen=True)
class Gaussians:
    """Initialisation and size of the Gaussian set."""

    init: str = _key("auto", "initialisation: auto | ply (points3d.ply) | hull (visual hull) | random")
    hull_masks: str = _key("all", "masks that carve the visual hull: all (every image source's views, the "
                                  "generated images' too) | real (the capture's views only)")
    count: int = _key(5_000, "initial number of Gaussians", "num_gaussians")
    max_count: int = _key(300_000, "cap on the number of Gaussians (a refinement that passes it drops the excess, "
                         "lowest opacity first)", "max_gaussians")


@dataclass(frozen=True)
class Densification:
    """Growing and pruning: the fields of gsplat's ``DefaultStrategy`` it sets (same names) and ``enabled``."""

    enabled: bool = _key(True, "grow and prune Gaussians (false keeps the count fixed)", "densify")
    prune_opa: float = _key(0.005, "opacity below which a Gaussian is pruned")
    grow_grad2d: float = _key(0.0010, "mean 2D gradient above which a Gaussian is densified",
                              "densify_grad_threshold")
    grow_scale3d: float = _key(0.01, "scale (fraction of the scene) above which a Gaussian is split, "
                               "not cloned", "percent_dense")
    refine_start_iter: int = _key(500, "first step of densification", "densify_from_iter")
    refine_stop_iter: int = _key(10_000, "last step of densification", "densify_until_iter")
    refine_every: int = _key(150, "steps between densifications", "densification_interval")
    reset_every: int = _key(1_000, "steps between opacity resets", "opacity_reset_interval")

    def strategy_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``gsplat.strategy.DefaultStrategy`` (every field but ``enabled``)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "enabled"}


@dataclass(frozen=True)
class Shading:
    """The subsurface-scattering MLP, the light and the background (a scene is built from this group)."""

    sss_width: int = _key(32, "hidden width of the subsurface-scattering MLP")
    sss_position_freqs: int = _key(4, "frequencies of the positional encoding of the Gaussian centre fed to the MLP "
                                   "(0: the raw centre only)")
    light_init: float = _key(-1.0, "initial log light scale (when not calibrated from the data)")
    light_init_from_data: bool = _key(True, "calibrate the initial light scale from the images")
    random_background: bool = _key(False, "train on random background colours")
    mixed_precision: bool = _key(True, "bfloat16 autocast of the subsurface-scattering MLP on CUDA")
    sss_angular_inputs: bool = _key(False, "also feed the MLP the cosines n.l, n.v and v.l (an angular prior shared "
                                    "by every Gaussian)")
    sss_light_depth: int = _key(0, "side in px of a depth map rendered at the light, from which each Gaussian's depth "
                                "below the lit surface is fed to the MLP (0: off)")
    sss_light_depth_every: int = _key(1, "training steps a light's depth map is reused for: rendered at the light's "
                                      "first use in each window of this many steps (1: at every use)")
    sss_visibility_gradient: bool = _key(True, "let the photometric loss train the SH visibility through the MLP's "
                                         "visibility input (false: the ray-traced term L_raytrace and, when on, the "
                                         "incident-light tie train it)")
    light_falloff: str = _key("none", "point-light falloff in the shading: none (as SSS-3DGS: the MLP learns it "
                              "from the light distance) | inverse_square (relative to the scene centre)")


@dataclass(frozen=True)
class Losses:
    """Loss weights (Eq. A.1-A.7, Tab. 3) and where the photometric loss compares images."""

    photometric_space: str = _key("srgb", "where the photometric error and D-SSIM compare images: srgb (as the "
                                  "SSS-3DGS release, which compares 8-bit sRGB values, and as the metrics) | "
                                  "linear radiance")
    photometric_error: str = _key("l1", "per-image error beside D-SSIM: l1 (Eq. A.1) | rmse (root mean squared "
                                  "error, what PSNR measures)")
    lambda_dssim: float = _key(0.492, "weight of the D-SSIM term of the photometric loss")
    lambda_lpips: float = _key(0.171, "weight of the LPIPS loss")
    lambda_mask: float = _key(0.1, "weight of the mask (alpha vs object mask) loss")
    lambda_mask_entropy: float = _key(0.1, "weight of the mask entropy loss")
    lambda_normal: float = _key(0.037, "weight of the normal consistency loss")
    lambda_visibility: float = _key(0.01, "weight of the ray-traced visibility loss")
    lambda_incident_light: float = _key(0.015, "weight of the incident light regulariser")
    lambda_enh: float = _key(0.005, "weight of the base colour enhancement loss")
    lambda_base_color: float = _key(0.002, "weight of the base colour prior")
    lambda_base_color_smooth: float = _key(0.005, "weight of the base colour smoothness")
    lambda_metallic_smooth: float = _key(0.007, "weight of the metalness smoothness")
    lambda_roughness_smooth: float = _key(0.003, "weight of the roughness smoothness")
    lambda_subsurfacedness_smooth: float = _key(0.002, "weight of the subsurfaceness smoothness")
    lambda_sil: float = _key(0.5, "weight of the multi-view silhouette loss")
    lambda_depth: float = _key(0.3, "weight of the multi-view depth loss")


@dataclass(frozen=True)
class MultiView:
    """Multi-view consistency sampling (Sec. D). Depth is smooth and sampled bilinearly, so the target views
    give the same constraint at a fraction of the resolution."""

    pairs_per_step: int = _key(2, "view pairs of the multi-view losses per step", "mv_pairs_per_step")
    pixels_per_pair: int = _key(512, "pixels sampled per view pair", "mv_pixels_per_pair")
    target_mode: str = _key("nearest-k", "target view choice: nearest-k | random", "mv_target_mode")
    nearest_k: int = _key(4, "nearest views a target is drawn from (nearest-k)", "mv_nearest_k")
    sil_threshold: float = _key(0.5, "alpha above which a pixel counts as inside the silhouette",
                                "mv_sil_threshold")
    occlusion_tol: float = _key(0.02, "relative depth tolerance of the occlusion test", "mv_occlusion_tol")
    charbonnier_eps: float = _key(0.0, "Charbonnier epsilon of the depth loss (0: L1)", "mv_charbonnier_eps")
    include_unobserved_views: bool = _key(False, "also draw targets among lattice views with no image (for the "
                                                 "depth term only: they have no silhouette)",
                                          "mv_include_unobserved_views")
    target_downscale: int = _key(2, "resolution divisor of the target views", "mv_target_downscale")
    sil_tolerance: float = _key(1.0, "silhouette value at and above which a reprojected point costs nothing "
                                     "(1: the plain 1 - S)", "mv_sil_tolerance")
    depth_tolerance: float = _key(0.0, "normalised depth residual that costs nothing (the expected depth's "
                                       "precision on tilted surfaces)", "mv_depth_tolerance")
    start_fraction: float = _key(0.0, "fraction of schedule.iterations before the multi-view losses start",
                                 "mv_start_fraction")
    source_gradient: str = _key("blend", "what the terms move through a source view's expected depth: blend "
                                         "(centres, opacities, scales, rotations) | centres (centres only)",
                                "mv_source_gradient")


@dataclass(frozen=True)
class RayTrace:
    """Ray-traced visibility supervision (L_raytrace): every ``every`` steps, on a random Gaussian subset."""

    every: int = _key(10, "steps between ray-traced visibility supervisions", "raytrace_every")
    gaussians: int = _key(1_024, "Gaussians ray-traced per supervision", "raytrace_gaussians")
    directions: int = _key(4, "directions traced per Gaussian", "raytrace_directions")


@dataclass(frozen=True)
class Runtime:
    """Device, logging and checkpoints. These small kernels gain little from a second CPU thread and lose 10x
    when cores are oversubscribed, hence one thread by default."""

    device: str = _key("auto", "auto | cpu | cuda[:i]")
    cpu_threads: int = _key(1, "torch intra-op threads on CPU (0: torch's default)")
    downscale: float = _key(1.0, "divide the image size by this factor")
    checkpoint_every: int = _key(500, "steps between checkpoints")
    keep_checkpoints: int = _key(2, "newest checkpoints kept on disk (0: every one, e.g. to score each step's model)")
    log_every: int = _key(25, "steps between scalar logs")
    image_log_every: int = _key(500, "steps between TensorBoard image logs")
    lpips_weights: str = _key("", "LPIPS (VGG) weights in safetensors (empty: $DIAMOND_SSS_LPIPS_WEIGHTS)")
    compile: str = _key("off", "off | inductor | aot_eager: torch.compile the render around the rasterizer and "
                                "the losses (fewer kernel launches on CUDA; the first steps compile)")


@dataclass(frozen=True)
class TrainConfig:
    """Hyperparameters of one reconstruction, one group per concern; frozen: resolved once
    (:func:`~diamond_sss.training.overrides.make_config`) and passed down, never edited on the way."""

    schedule: Schedule = field(default_factory=Schedule)
    lr: LearningRates = field(default_factory=LearningRates)
    gaussians: Gaussians = field(default_factory=Gaussians)
    densify: Densification = field(default_factory=Densification)
    shading: Shading = field(default_factory=Shading)
    losses: Losses = field(default_factory=Losses)
    multiview: MultiView = field(default_factory=MultiView)
    raytrace: RayTrace = field(default_factory=RayTrace)
    runtime: Runtime = field(default_factory=Runtime)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Nested ``{group: {field: value}}`` (the layout of a run's ``config.json``)."""
        return dataclasses.asdict(self)

    def get(self, key: str) -> Any:
        """The value of a dotted (``losses.lambda_dssim``) or flat (``lambda_dssim``) key."""
        group, name = canonical_key(key).split(".")
        return getattr(getattr(self, group), name)

    def flat(self) -> dict[str, Any]:
        """``{flat name: value}``: the single-level layout of earlier runs and tuning studies."""
        return {flat: self.get(dotted) for flat, dotted in FLAT_KEYS.items()}


PRESETS: dict[str, TrainConfig] = {
    "diamond": TrainConfig(),
    "paper": TrainConfig(),
    "sss3dgs": TrainConfig(
        losses=Losses(lambda_dssim=0.2, lambda_lpips=0.2, lambda_normal=0.02, lambda_visibility=0.01,
                      lambda_incident_light=0.02, lambda_base_color=0.005, lambda_base_color_smooth=0.006,
                      lambda_metallic_smooth=0.002, lambda_roughness_smooth=0.002,
                      lambda_subsurfacedness_smooth=0.002, lambda_sil=0.0, lambda_depth=0.0),
        densify=Densification(refine_every=100, reset_every=3_000, refine_start_iter=500,
                              refine_stop_iter=15_000, grow_grad2d=0.0002),
    ),
}
"""The presets (``paper`` is ``diamond``'s other name); :func:`~diamond_sss.training.overrides.make_config` copies
them, never changes them."""

AUTO_PRESET = "auto"
"""The default preset of ``diamond-sss train | run | config``: ``diamond`` with the settings measured for the run's
length and capture (:func:`short_schedule`; what ``--short-run`` gave before it became the default). Measured on a
held-out dense capture: at 3,000 steps 37.29 dB against the ``diamond`` preset's schedule scaled to them, 31.81 dB; at
1,000 steps on a 2-core CPU 35.79 dB in 180 s (5.2k Gaussians) against 28.96 dB in 645 s (15.5k)
(DIAMOND-SSS issue 60). The Tab. 3 / Tab. 4 settings stay the named presets."""


GROUPS: dict[str, type] = typing.get_type_hints(TrainConfig)
"""Group name -> its dataclass."""

FIELDS: dict[str, dataclasses.Field] = {f"{group}.{f.name}": f for group, kind in GROUPS.items()
                                        for f in fields(kind)}
"""Dotted key -> dataclass field (its ``metadata`` holds ``help`` and, where it differs, ``flat``)."""

FLAT_KEYS: dict[str, str] = {f.metadata.get("flat", f.name): dotted for dotted, f in FIELDS.items()}
"""Flat name (the single-level layout of earlier runs and tuning studies) -> dotted key."""


def field_types() -> dict[str, type]:
    """Dotted key -> Python type of every :class:`TrainConfig` field."""
    return {f"{group}.{name}": hint for group, kind in GROUPS.items()
            for name, hint in typing.get_type_hints(kind).items()}


PIPELINE_KEYS: dict[str, str] = {"losses.synthetic_weight": "synthetic_weight"}
"""Keys of earlier configurations that are pipeline settings since DIAMOND-SSS issue 61 (dotted key -> the
:class:`~diamond_sss.pipeline.config.PipelineConfig` field, also their flat name): a run's ``config.json`` that
records one loads without it (:func:`~diamond_sss.training.overrides.load_run_config`); given anywhere else, it is
refused, naming the pipeline's flag."""


def canonical_key(key: str) -> str:
    """The dotted key of a dotted or flat ``key``; unknown keys raise ``ValueError`` naming similar keys, the
    :data:`PIPELINE_KEYS` naming the pipeline's flag."""
    key = key.strip()
    if key in FIELDS:
        return key
    if key in FLAT_KEYS:
        return FLAT_KEYS[key]
    if (setting := PIPELINE_KEYS.get(key, key if key in PIPELINE_KEYS.values() else None)) is not None:
        raise ValueError(f"config key '{key}' is a setting of the pipeline, not of a reconstruction: give it to "
                         f"`diamond-sss run` as --{setting.replace('_', '-')} (`train` has no generated images)")
    names = (*FIELDS, *FLAT_KEYS)
    stem = key.split(".")[-1].split("_")[-1]
    close = difflib.get_close_matches(key, names, n=6, cutoff=0.7)
    close = [*close, *(name for name in names if stem in name and name not in close)][:6]
    raise ValueError(f"unknown config key '{key}'" + (f"; similar keys: {close}" if close else ""))


SCHEDULE_KEYS = ("lr.position_delay_steps", "lr.position_max_steps", "lr.decay_step", "lr.sss_warmup_steps",
                 "densify.refine_start_iter", "densify.refine_stop_iter", "densify.refine_every",
                 "densify.reset_every", "runtime.checkpoint_every", "runtime.log_every", "runtime.image_log_every")
"""Step-valued keys: a run of another length scales them with :func:`scale_schedule`."""

SHORT_SCHEDULE: dict[str, int] = {
    "iterations": 1000, "position_lr_max_steps": 1000, "densify_from_iter": 250, "densify_until_iter": 850,
    "densification_interval": 125, "opacity_reset_interval": 10_001, "log_every": 50, "checkpoint_every": 500,
    "lr_decay_step": 700, "sss_lr_warmup_steps": 100,
}
"""Tab. 3's schedule compressed for a run of a few hundred steps (demo, benchmarks), at 1000 steps:
densification from 25% to 85% of the run every 12.5%, no opacity reset (too short for the Gaussians to
recover), the position learning rate decaying over the run, the step decay of every other learning rate at 70%
of the run (the paper's is at 50k of 80-100k steps; the preset's 50k is never reached by a 10k-step run), and
the MLP's (5x Tab. 3's, :data:`SHORT_RUN_MODEL`) warmed up over the first 10%: at the full rate from the first
step, Adam can drive every weight the same way while the image is too bright, until the residual's sigmoid and the
incident light's ReLU saturate at 0 for every input and the render stays black (seen on a 30-image pipeline run)."""

CPU_BUDGET: dict[str, int] = {"batch_size": 1, "num_gaussians": 3_000, "max_gaussians": 8_000,
                              "mv_pairs_per_step": 1, "mv_pixels_per_pair": 256, "raytrace_gaussians": 512}
"""Batch 1, 3k initial Gaussians capped at 8k, lighter multi-view and ray-tracing sampling (64x64 on a CPU)."""

SHORT_RUN_MODEL: dict[str, Any] = {"sss_lr": 0.005, "sss_width": 64, "lambda_incident_light": 0.0,
                                   "lr_decay_factor": 0.3, "sss_light_depth": 64, "sss_light_depth_every": 10,
                                   "sss_angular_inputs": True}
"""What a run 80-100x shorter than the paper's (1000 steps, not 80-100k) needs, each measured on the demo
object (benchmarks/RESULTS.md, issue 17): the MLP learns 5x faster (+1.6 dB) and 2x wider (+0.5 dB), the
incident light is not tied to the SH visibility, which ~10 ray-traced updates per Gaussian leave near its
initial value (the tie then forbids shadows: +0.5 dB), and the step decay multiplies the rates by 0.3, not 0.1
(+0.3 / +0.4 dB over no decay on two seeds; 0.1: +0.05 dB). The MLP also sees each Gaussian's depth below the
lit surface from a 64-px depth map rendered at the light (:mod:`diamond_sss.shading.light_depth`): +1.5 to +2.0
dB on three seeds of the dense demo object, all of it under novel lights, and -0.2 to +0.7 dB at 9 images (a
48-px map; 64 px gave a further +0.23 dB mean on three dense seeds, +0.10 at 10k steps, +0.31 dB mean in three
9-image pipeline runs, with the cast shadows darker, at about the same cost: the map's cost grows with the
Gaussians, not its pixels). A light's map is rendered once in each window of 10 steps and reused for the rest
(``sss_light_depth_every``): the demo's 9-image ``sss3dgs`` run takes 15% less time (216 -> 185 s) for 19.19 -> 19.17
dB, and the demo's rows move within their seed spread (19.19 | 21.47 | 30.33 -> 19.17 | 21.69 | 30.28 dB). The MLP
sees the cosines n.l, n.v, v.l (an angular prior shared by every Gaussian): dense, +0.84 / +0.26 / +0.23 dB on three
seeds of the demo object, all of it under novel lights; sparse, on held-out objects of another rig given as only
their 9 images, the SSS-3DGS baseline +2.34 / +0.38 / +2.20 / +1.52 dB (knot/jade, blob/wax, knot/skin, bust/soap)
and ``--augment repair`` +1.57 / +0.22 over the same runs without them (the paper's stages -0.49 / -0.83: they lost
0.55-0.66 dB on the project's own objects too; benchmarks/RESULTS.md, session 45)."""

DENSE_SHORT_RUN: dict[str, Any] = {"batch_size": 2, "photometric_error": "rmse"}
"""A short run over a dense capture (the demo object's 960 images: at batch 1, 1000 steps draw each image about
once) draws 2 images per step: +0.7 / +1.2 dB on two seeds for 1.3x the time; and its photometric loss takes each
image's RMSE, what PSNR measures, in place of Eq. A.1's L1: +0.21 / +0.20 dB on two seeds at 1000 steps, +0.29 /
+0.26 / +0.23 on three at 10,000. Sparse runs keep batch 1 (their few images are each drawn 100 times or more; batch
2 cost 0.4 and 1.2 dB in the demo's 9-image rows); a sparse run on the real images alone keeps Eq. A.1's L1, as the
SSS-3DGS baseline has it, and the pipeline's final reconstruction takes the RMSE (:data:`PIPELINE_FINAL_RUN`)
(benchmarks/RESULTS.md, issues 17 and 18)."""

SPARSE_FROM_SSS3DGS = ("densify_grad_threshold", "lambda_dssim", "lambda_normal", "lambda_base_color",
                       "lambda_base_color_smooth", "lambda_metallic_smooth", "lambda_roughness_smooth")
"""Keys a short run over a sparse capture takes from the ``sss3dgs`` preset (supplement Tab. 4 "Original": a 5x lower
densification threshold, D-SSIM 0.2 instead of 0.49, lighter material priors), whatever its preset; the multi-view
terms stay the preset's. Measured on four held-out objects of another rig at 9 images, 1000 steps (issue 58,
benchmarks/RESULTS.md, session 46): the ``diamond`` preset with the terms 17.52 / 18.41 / 18.35 / 21.17 dB (knot/jade,
blob/wax decide; knot/skin, bust/soap report), with these keys 17.93 / 19.81 / 18.39 / 22.32 (+0.41 / +1.40 / +0.04 /
+1.15). Dense captures keep the ``diamond`` preset's (its settings were measured there, issue 17), and so does the
pipeline's final reconstruction (real and generated images): with these keys after render repair +0.15 / +0.67 dB
on the deciding objects but -0.04 / +0.02 on the others, whose mask IoU fell (0.917 -> 0.905, 0.959 -> 0.942)."""

SPARSE_MULTIVIEW: dict[str, Any] = {"mv_source_gradient": "centres"}
"""A short run over a sparse capture (not the pipeline's final reconstruction) lets its multi-view terms move only
the Gaussian centres through the source views' depth (``multiview.source_gradient``). Through the blending weights
the silhouette term lowers the front Gaussians' opacity, which moves the expected depth behind the surface (bias
+0.03 to +0.13 scene units, radius 1). Measured on held-out objects given as their 9 images, 1000 steps, the
``sss3dgs`` weights, both terms (issue 58, benchmarks/RESULTS.md, session 47): depth error .087 / .127 / .083 / .090
-> .063 / .062 / .061 / .044 (terms off: .061 / .060 / .057 / .036); PSNR 17.93 / 19.81 / 18.39 / 22.32 -> 17.98 /
20.03 / 18.72 / 21.73 (knot/jade, blob/wax decide; knot/skin, bust/soap report; mean 19.61 both), on training seed 1
17.56 / 19.88 / 18.75 / 22.49 -> 17.98 / 20.06 / 18.30 / 21.54 (the deciding objects gain, bust/soap loses 0.6-0.95;
mean of the 8 runs 19.64 -> 19.54, terms off 19.52); at 30 images, 2 seeds, mean 24.44 -> 24.25 (off 24.21), depth
error .070 / .087 -> .052 / .054. Its cost, a second geometry pass over the batch views: 200 steps on the demo's 9
images (64 px, 8k Gaussians, one CPU thread) 24-26 s -> 33-34 s. The terms stay on there: end to end (session 53, 9
images, ``train`` with them off against on) they scored +0.06 dB mean on those four objects (-0.37 / +0.10 / 0.00 /
+0.50) but +0.54 / +0.47 (mask IoU +0.02) on the knots of a rig framing the object at half that scale."""

DENSE_MIN_IMAGES = 100
"""A run whose regime selects at least this many training images takes a dense capture's short-run settings
(:data:`DENSE_SHORT_RUN`); fewer, a sparse capture's. Measured: 9, 30 and 40 images (all views under one light
each) are sparse captures (batch 2 cost 0.4 and 1.2 dB in the demo's 9-image rows; on a held-out object's 9 images
the dense settings scored 18.23 dB, the sparse ones 18.22), the demo's 960 images a dense one; counts between 40 and
960 are not measured (benchmarks/RESULTS.md, issues 17, 57 and 60)."""

PIPELINE_FINAL_RUN: dict[str, Any] = {"photometric_error": "rmse", "lambda_sil": 0.0, "lambda_depth": 0.0,
                                      "lambda_mask": 0.5}
"""The DIAMOND-SSS pipeline's final reconstruction over a sparse capture (its real images and a few hundred generated
ones) takes each image's RMSE as its photometric error, as a dense capture does (:data:`DENSE_SHORT_RUN`). Measured
with the shipped diffusion models on issue 18's objects, 1000 steps: 30 images +0.21 dB mean over two draws of the
images (bunny, torus, blob: -0.03 / +0.18 / +0.30 and +0.43 / -0.01 / +0.39), 9 images +0.05 / +0.25 / -0.12 /
-0.06 (bunny, torus, blob, bust; mean +0.03), the torus's other two draws +0.18 / -0.21 (benchmarks/RESULTS.md, issue
18). With the diffusion models of session 25 it had cost the demo's 9-image pipeline 0.41 dB.

It also leaves the multi-view terms out and weighs the mask loss (Eq. A.4) 0.5 instead of 0.1: the silhouette term's
dB there is a uniform erosion that moves the whole surface behind the true one (its ``1 - S`` pulls every point in a
target mask's soft edge inwards), and a 5x mask weight thins the same halo without it. Measured on held-out objects of
another rig (render repair, 1000 steps, against the terms at the preset's weights; DIAMOND-SSS issue 58,
benchmarks/RESULTS.md, sessions 56-57): PSNR -0.13 dB mean over 12 runs (9 images: knot/jade, blob/wax decide -0.28 /
+0.32; knot/skin +0.17, bust/soap -0.66 and -0.55 on two seeds, a far rig's knot/marble -0.06; 30 images -0.61 /
+0.44 and on seed 1 -0.66 / +0.48; 9 images as a lattice -0.46 / +0.34), under the seed spread, for an
expected-depth error 15-50% lower in all 12 and a higher mask IoU in 9. The terms at the preset's weights are ``--set lambda_sil=0.5 --set lambda_depth=0.3
--set lambda_mask=0.1`` away (``--preset diamond``: the paper's settings whole)."""

DENSE_LONG_RUN_STEPS = 3_000
"""From this many steps a short run over a dense capture also takes :data:`DENSE_LONG_RUN`."""

DENSE_LONG_RUN: dict[str, Any] = {"sss_visibility_gradient": False, "average_last": 0.1, "lambda_mask": 0.03}
"""A dense short run of 3,000 steps or more trains the SH visibility with the ray-traced term alone: the
photometric loss no longer reaches it through the MLP's visibility input, through which it over-fits the 24
training lights in long runs (demo object, 10k steps, three seeds: +0.29 dB mean test PSNR, every seed gaining,
most of it under the low novel lights; as much as freezing the visibility, which drops the method's learned
visibility). Its saved model is the mean of the last 10% of the steps' parameters
(:mod:`diamond_sss.training.averaging`): +0.20 / +0.06 / +0.17 dB on three seeds at 10k, the training images and
both kinds of novel images alike. Both together at 3,000 steps: +0.17 / +0.09 dB on two seeds. Its mask loss (Eq.
A.4) weighs 0.03, not 0.1: the weaker alpha target lets the outline's opacity and colour settle together, +0.07 /
+0.06 / +0.10 dB on three seeds at 10k (mean 32.01) for mask IoU 0.956 -> 0.949, +0.08 / +0.07 dB at 3,000
steps (a weight of 0.5 does the reverse: -0.24 dB, IoU 0.975). At 1000 steps the first two cost (the visibility
-0.12 dB on three seeds; averaging the last 100 steps, from 50 steps after densification's end while the MLP still
learns, -0.05 / -0.04 dB on two) and the mask weight is not measured, so shorter runs keep the photometric
gradient, the last step's parameters and the preset's mask weight (benchmarks/RESULTS.md, issue 17)."""


SCHEDULE_FLOORS: dict[str, int] = {"densify.refine_every": 10, "densify.reset_every": 200}
"""Fewest steps a scaled run keeps for processes that take optimisation steps, whatever the run's length:
the gradient statistics of one densification (below ~10 steps a Gaussian is seen once or twice and the
noisy statistic densifies nearly all of them: 300k Gaussians after 50 steps) and the recovery of the
opacities after a reset (~100 Adam steps at ``lr.opacity`` to climb back from 0.01)."""


def scale_schedule(values: Mapping[str, Any], scale: float,
                   floors: Mapping[str, int] = SCHEDULE_FLOORS) -> dict[str, Any]:
    """``values`` (dotted or flat keys, kept as given) with every :data:`SCHEDULE_KEYS` value times ``scale``,
    rounded down, at least 1 (0 stays 0) and never below ``min(value, floors[dotted key])``.

    The one schedule scaler: ``train --iterations``, :func:`short_schedule` and the tuning trials (which pass
    no floors, so that every searched value stays distinct) use it.
    """
    if not scale > 0:
        raise ValueError(f"schedule scale must be positive, got {scale}")
    dotted = {key: canonical_key(key) for key in values}
    return {key: max(1, min(value, floors.get(dotted[key], 1)), math.floor(value * scale + 1e-9))
            if dotted[key] in SCHEDULE_KEYS and value > 0 else value for key, value in values.items()}


def schedule_for(values: Mapping[str, Any], iterations: int) -> dict[str, Any]:
    """``iterations`` and the schedule keys of ``values`` (which holds its own ``iterations``; dotted or flat
    keys, kept as given) scaled to it."""
    if iterations <= 0:
        raise ValueError(f"iterations must be positive, got {iterations}")
    given = {canonical_key(key): key for key in values}
    schedule = {given[key]: values[given[key]] for key in SCHEDULE_KEYS if key in given}
    length = given["schedule.iterations"]
    return {length: iterations, **scale_schedule(schedule, iterations / values[length])}


def short_schedule(iterations: int, dense: bool = False, pipeline_final: bool = False) -> dict[str, Any]:
    """Overrides for a reconstruction of ``iterations`` steps at 64x64 on a CPU: :data:`SHORT_SCHEDULE`
    scaled to ``iterations``, with :data:`CPU_BUDGET` (and :data:`DENSE_SHORT_RUN` for a ``dense`` capture, from
    :data:`DENSE_LONG_RUN_STEPS` on with :data:`DENSE_LONG_RUN` too; :data:`PIPELINE_FINAL_RUN` for the
    ``pipeline_final`` reconstruction of a sparse capture, :data:`SPARSE_FROM_SSS3DGS` and
    :data:`SPARSE_MULTIVIEW` for any other) and
    :data:`SHORT_RUN_MODEL`."""
    budget = {**CPU_BUDGET, **DENSE_SHORT_RUN} if dense else CPU_BUDGET
    sparse = {} if dense or pipeline_final else {
        **{key: PRESETS["sss3dgs"].flat()[key] for key in SPARSE_FROM_SSS3DGS}, **SPARSE_MULTIVIEW}
    long_run = DENSE_LONG_RUN if dense and iterations >= DENSE_LONG_RUN_STEPS else {}
    final = PIPELINE_FINAL_RUN if pipeline_final else {}
    return {**schedule_for(SHORT_SCHEDULE, iterations), **budget, **SHORT_RUN_MODEL, **sparse, **long_run, **final}
