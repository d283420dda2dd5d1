"""Configuration of the relighting diffusion model (pixel-space default or latent space on a pretrained SD) and
of its fine-tuning (no torch: the command line derives its options from them)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from diamond_sss.diffusion.common.schedulers import SchedulerConfig

LIGHT_CODE_DIM = 10
"""9 SH coefficients (degree 2) of the light direction in the source camera frame + the light distance."""

CONDITIONING_CHANNELS = 8
"""Source image (3), depth (1), camera-space normals (3), mask (1): what callers give the model."""

HINT_CHANNELS = 3
"""The shading hint (``hint.py``) the model appends to the conditioning image when ``shading_hint`` is on."""

TUPLE_KEYS = ("block_out_channels", "hint_blurs", "hint_wraps")
"""Config fields stored as JSON lists."""

LEGACY_HINT_BLUR_KEY = "hint_blur"
"""Models saved before the scattering fit had one blur and no wrap: read as ``hint_blurs=(b,), hint_wraps=(0,)``."""


@dataclass(frozen=True)
class RelightModelConfig:
    """Architecture of a relighting model built by this project (``space="pixel"``) or on SD (``"latent"``).

    Attributes:
        space: ``"pixel"`` (denoise sRGB images in [-1, 1]) or ``"latent"`` (denoise VAE latents).
        resolution: image side the model works at (pixels; conditioning maps are resized to it).
        block_out_channels: UNet / ControlNet widths per resolution level (pixel space).
        attention_levels: how many of the lowest-resolution levels have (self- and cross-) attention.
        layers_per_block: ResNet layers per level.
        attention_head_dim: channels per attention head.
        cross_attention_dim: width of the light tokens the cross-attention layers read.
        light_tokens: number of cross-attention tokens made from the light code(s).
        use_source_light: also give the source light's code (timestep embedding and tokens).
        shading_hint: append the directional Lambertian re-shading (``hint.py``) to the ControlNet's input.
        hint_blurs: screen-space diffusions of the hint's shading to choose from, Gaussians of
            ``blur * resolution`` pixels (``hint.py``; 1/32 = 2 px at 64 px, 0 = none).
        hint_wraps: wrap-lighting offsets of the hint's shading to choose from (``hint.py``; 0 = Lambertian).
            Each image's pair is fitted to its source image; single values fix the scattering.
        residual: denoise ``target - hint`` (in the denoised space) instead of the target itself, so the
            network learns the correction to Lambertian shading; needs ``shading_hint``.
        norm_num_groups: GroupNorm groups.
        scheduler: training noise schedule (v-prediction).
    """

    space: str = "pixel"
    resolution: int = 64
    block_out_channels: tuple[int, ...] = (16, 32, 64)
    attention_levels: int = 1
    layers_per_block: int = 1
    attention_head_dim: int = 8
    cross_attention_dim: int = 64
    light_tokens: int = 4
    use_source_light: bool = False
    shading_hint: bool = True
    hint_blurs: tuple[float, ...] = (1.0 / 64.0, 1.0 / 32.0, 3.0 / 64.0, 1.0 / 16.0, 3.0 / 32.0)
    hint_wraps: tuple[float, ...] = (0.0, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0)
    residual: bool = True
    norm_num_groups: int = 8
    scheduler: SchedulerConfig = field(default_factory=SchedulerConfig)

    def __post_init__(self) -> None:
        if self.space not in ("pixel", "latent"):
            raise ValueError(f"space must be 'pixel' or 'latent', got {self.space!r}")
        if self.resolution % (2 ** (len(self.block_out_channels) - 1)) != 0:
            raise ValueError(
                f"resolution {self.resolution} must be divisible by "
                f"2^(levels - 1) = {2 ** (len(self.block_out_channels) - 1)}"
            )
        if not 1 <= self.attention_levels <= len(self.block_out_channels):
            raise ValueError(
                f"attention_levels must be in [1, {len(self.block_out_channels)}], "
                f"got {self.attention_levels}"
            )
        if self.residual and not self.shading_hint:
            raise ValueError(
                "residual=True denoises the offset from the shading hint: it needs shading_hint=True"
            )
        for key in ("hint_blurs", "hint_wraps"):
            values = getattr(self, key)
            if not values or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
                raise ValueError(f"{key} must be a non-empty list of numbers, got {values!r}")
        if min(self.hint_blurs) < 0.0 or min(self.hint_wraps) < 0.0:
            raise ValueError(
                f"hint_blurs and hint_wraps must be >= 0, got {self.hint_blurs} and {self.hint_wraps}"
            )
        if self.scheduler.prediction_type != "v_prediction":
            raise ValueError("the relighting model is trained with v-prediction")

    @property
    def light_input_dim(self) -> int:
        """Length of the code fed to the timestep embedding and the token MLP."""
        return LIGHT_CODE_DIM * (2 if self.use_source_light else 1)

    @property
    def controlnet_channels(self) -> int:
        """Channels of the ControlNet's conditioning image (the callers' 8, plus the hint when used)."""
        return CONDITIONING_CHANNELS + (HINT_CHANNELS if self.shading_hint else 0)

    def to_dict(self) -> dict:
        out = asdict(self)
        for key in TUPLE_KEYS:
            out[key] = list(out[key])
        return out

    @classmethod
    def from_dict(cls, data: dict) -> RelightModelConfig:
        known = {f.name for f in fields(cls)} | {LEGACY_HINT_BLUR_KEY}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown relighting model config keys: {unknown}")
        data = dict(data)
        if LEGACY_HINT_BLUR_KEY in data:
            data.setdefault("hint_blurs", [data.pop(LEGACY_HINT_BLUR_KEY)])
            data.setdefault("hint_wraps", [0.0])
        for key in TUPLE_KEYS:
            if key in data:
                data[key] = tuple(data[key])
        if isinstance(data.get("scheduler"), dict):
            data["scheduler"] = SchedulerConfig(**data["scheduler"])
        return cls(**data)


@dataclass(frozen=True)
class RelightLossWeights:
    """Weights of the terms above (``lpips`` only counts when an LPIPS network is given)."""

    v_mse: float = 1.0
    l1: float = 0.5
    ssim: float = 0.2
    lpips: float = 0.1
    cycle: float = 0.2
    low_frequency: float = 0.5
    low_frequency_kernel: int = 4


@dataclass(frozen=True)
class RelightAugmentConfig:
    """Augmentations of each training pair (module doc).

    Attributes:
        mirror: mirror half of the pairs left-right.
        exposure: log2 range ``e`` of the shared gain (1 = from 1/2 to 2 times; 0 = off).
        tint: natural-log range ``t`` of the per-channel gains (0.15 = about +-16%; 0 = off).
        permute_colors: permute the colour channels of each pair by one of the 6 permutations, uniformly.
    """

    mirror: bool = True
    exposure: float = 1.0
    tint: float = 0.15
    permute_colors: bool = True

    def __post_init__(self) -> None:
        if self.exposure < 0.0 or self.tint < 0.0:
            raise ValueError(f"exposure and tint must be >= 0, got {self.exposure} and {self.tint}")

    @classmethod
    def off(cls) -> RelightAugmentConfig:
        """No augmentation: every pair as rendered."""
        return cls(mirror=False, exposure=0.0, tint=0.0, permute_colors=False)


@dataclass(frozen=True)
class RelightTrainConfig:
    """Fine-tuning settings.

    Attributes:
        steps: optimisation steps.
        batch_size: (source, target) pairs per step.
        learning_rate: AdamW peak learning rate, reached after ``warmup_steps`` (linear), then cosine to 10%.
        warmup_steps: linear warm-up length.
        weight_decay: AdamW weight decay.
        ema_decay: EMA decay of the shipped weights.
        cycle_every: compute the cycle-consistency term every this many steps (it doubles a step's cost).
        checkpoint_every: steps between atomic checkpoints.
        keep_checkpoints: newest checkpoints kept (0: every one).
        log_every: steps between log lines.
        max_grad_norm: clip the gradients to this global L2 norm before each optimiser step (None: not clipped).
        seed: seed of initialisation, batches, timesteps and noise.
        mixed_precision: accelerate's ``"no"``, ``"fp16"`` or ``"bf16"`` (GPU).
        time_limit_s: stop early (checkpoint and weights written) once this much wall time (s) has passed since
            the fine-tune started, loading included.
        losses: loss weights.
        augment: mirror / exposure / tint / colour-permutation augmentation of the pairs (``augment.py``).
    """

    steps: int = 2000
    batch_size: int = 8
    learning_rate: float = 5e-4
    warmup_steps: int = 50
    weight_decay: float = 1e-4
    ema_decay: float = 0.995
    cycle_every: int = 4
    checkpoint_every: int = 100
    keep_checkpoints: int = 2
    log_every: int = 10
    max_grad_norm: float | None = 1.0
    seed: int = 0
    mixed_precision: str = "no"
    time_limit_s: float | None = None
    losses: RelightLossWeights = field(default_factory=RelightLossWeights)
    augment: RelightAugmentConfig = field(default_factory=RelightAugmentConfig)
