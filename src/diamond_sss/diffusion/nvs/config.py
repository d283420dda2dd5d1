"""Configurations of the novel-view model and its fine-tuning (no torch: the command line derives its options
from them)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from diamond_sss.diffusion.common.schedulers import SchedulerConfig

WARP_CHANNELS = 5
"""Channels of the warp hint: warped RGBA and validity."""


@dataclass
class NVSConfig:
    """Architecture and noise schedule of the novel-view model.

    ``beta_schedule="scaled_linear"`` is the LDM/Free3D "linear" schedule (betas linear in sqrt space,
    ``0.00085 -> 0.012`` over 1000 steps). ``warp_hint`` adds the geometric warp hint to the UNet input
    (pixel space only); its reference image and depth are used at ``warp_supersample`` times the image size,
    so surfaces magnified by the new view leave no cracks. ``hint_residual`` denoises ``x0 - m w`` instead
    of ``x0`` (``w`` the warped reference in model space, ``m`` its validity).

    Attributes:
        space: pixel (small offline default) or latent (needs ``vae_path``).
        image_size: side of the generated images (pixels; latent space: 8x the latent side).
        prediction_type: epsilon (Free3D's objective) or v_prediction (steadier for small pixel models).
        hint_residual: denoise the residual from the warped reference where it is valid (needs the warp hint).
        block_out_channels: UNet channels per resolution level, one per down/up block (the model's width).
        layers_per_block: ResNet (and attention) layers per UNet block (the model's depth).
    """

    space: str = "pixel"
    image_size: int = 32
    image_channels: int = 4
    latent_channels: int = 4
    latent_scale: float = 0.18215
    vae_path: str | None = None
    block_out_channels: tuple[int, ...] = (32, 64, 64)
    down_block_types: tuple[str, ...] = ("DownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D")
    up_block_types: tuple[str, ...] = ("CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "UpBlock2D")
    layers_per_block: int = 1
    attention_head_dim: int = 8
    norm_num_groups: int = 8
    cross_attention_dim: int = 64
    embed_dim: int = 64
    encoder_channels: tuple[int, ...] = (32, 64)
    num_train_timesteps: int = 1000
    beta_start: float = 0.00085
    beta_end: float = 0.012
    beta_schedule: str = "scaled_linear"
    prediction_type: str = "epsilon"
    condition_dropout: float = 0.05
    warp_hint: bool = True
    warp_supersample: int = 2
    hint_residual: bool = False

    def __post_init__(self) -> None:
        if self.space not in ("pixel", "latent"):
            raise ValueError(f"space must be 'pixel' or 'latent', got {self.space!r}")
        if self.prediction_type not in ("epsilon", "v_prediction"):
            raise ValueError(
                f"prediction_type must be 'epsilon' or 'v_prediction', got {self.prediction_type!r}"
            )
        if self.warp_hint and self.space != "pixel":
            raise ValueError("warp_hint is a pixel-space hint: use space='pixel' or warp_hint=False")
        if self.hint_residual and not self.warp_hint:
            raise ValueError(
                "hint_residual denoises the residual from the warp hint: it needs warp_hint=True"
            )
        if self.warp_supersample < 1:
            raise ValueError(f"warp_supersample must be >= 1, got {self.warp_supersample}")
        if self.space == "latent" and self.image_size % 8:
            raise ValueError(f"latent space needs an image size divisible by 8, got {self.image_size}")
        for name in ("block_out_channels", "down_block_types", "up_block_types", "encoder_channels"):
            setattr(self, name, tuple(getattr(self, name)))
        levels = len(self.down_block_types)
        if len(self.block_out_channels) != levels or len(self.up_block_types) != levels:
            raise ValueError(
                f"block_out_channels needs one entry per UNet level ({levels}: {self.down_block_types}), "
                f"got {self.block_out_channels}"
            )
        bad = [c for c in self.block_out_channels if c <= 0 or c % self.norm_num_groups]
        if bad:
            raise ValueError(
                f"block_out_channels must be positive multiples of norm_num_groups={self.norm_num_groups}, "
                f"got {self.block_out_channels} ({bad} are not)"
            )
        if self.layers_per_block < 1:
            raise ValueError(f"layers_per_block must be >= 1, got {self.layers_per_block}")

    @property
    def model_channels(self) -> int:
        """Channels the UNet denoises (RGBA pixels or VAE latents)."""
        return self.latent_channels if self.space == "latent" else self.image_channels

    @property
    def model_size(self) -> int:
        """Spatial side of what the UNet denoises."""
        return self.image_size // 8 if self.space == "latent" else self.image_size

    @property
    def input_channels(self) -> int:
        """UNet input channels: noisy target, reference and (with ``warp_hint``) warped RGBA + validity."""
        return 2 * self.model_channels + (WARP_CHANNELS if self.warp_hint else 0)

    @property
    def warp_source_size(self) -> int:
        """Side of the reference image and depth map the warp hint is splatted from."""
        return self.image_size * self.warp_supersample

    @property
    def scheduler(self) -> SchedulerConfig:
        """The noise schedule (training DDPM and sampling DDIM; no zero-terminal-SNR rescaling)."""
        return SchedulerConfig(
            num_train_timesteps=self.num_train_timesteps,
            beta_start=self.beta_start,
            beta_end=self.beta_end,
            beta_schedule=self.beta_schedule,
            prediction_type=self.prediction_type,
            rescale_betas_zero_snr=False,
        )

    @property
    def sample_clip_range(self) -> float | None:
        """Clip of the clean estimate at every DDIM step: ``[-1, 1]`` in pixel space (``[-2, 2]`` for a residual
        from the warp hint), none in latent space."""
        if self.space != "pixel":
            return None
        return 2.0 if self.hint_residual else 1.0

    @classmethod
    def from_dict(cls, data: dict) -> NVSConfig:
        """Config from ``config.json``; files written before the warp hint existed have ``warp_hint=False``."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown NVS config keys {unknown}")
        return cls(**{"warp_hint": False, **data})


@dataclass
class FinetuneConfig:
    """Fine-tuning hyper-parameters.

    Attributes:
        steps: optimisation steps.
        objects_per_batch: objects per step (one sequence each).
        views_per_object: target views per object (all share one timestep).
        learning_rate: AdamW learning rate after warm-up.
        warmup_steps: linear warm-up steps.
        weight_decay: AdamW weight decay.
        ema_decay: decay of the EMA weights that are saved.
        gradient_checkpointing: recompute activations of every ResNet/transformer block in the backward pass.
        seed: seed of the model initialisation and of the sampled training stream.
        checkpoint_every: steps between atomic checkpoints.
        keep_checkpoints: newest checkpoints kept (0: every one).
        log_every: steps between log lines.
        max_grad_norm: clip the gradients to this global L2 norm before each optimiser step (None: not clipped, as
            the shipped prior was trained).
        time_limit_s: stop early, with a checkpoint and the EMA weights written, once this much wall time (s)
            has passed since the fine-tune started, loading included (a time-boxed run: the steps that fit).
        mixed_precision: accelerate's ``"no"``, ``"fp16"`` (GPU) or ``"bf16"``: the forward pass in autocast.
        init_from: a model folder (``finetune-nvs``'s ``model``, ``convert-free3d``'s output) whose weights start
            the run instead of a random initialisation; its architecture must be ``model``'s. A run resumed from
            a checkpoint continues from the checkpoint's weights.
        depth_noise_share: share of the references whose depth (the warp hint's input) is perturbed to look like
            a sparse reconstruction's render (``diffusion/nvs/depth_noise.py``); 0: the stored true depth.
        depth_noise_relative: the largest standard deviation of the perturbation's smooth relative depth error.
        depth_noise_edge_px: the largest dilation or erosion of the depth's outline (pixels of the generated image).
        model: architecture and noise schedule.
    """

    steps: int = 1000
    objects_per_batch: int = 4
    views_per_object: int = 4
    learning_rate: float = 1e-4
    warmup_steps: int = 100
    weight_decay: float = 0.0
    ema_decay: float = 0.999
    gradient_checkpointing: bool = True
    seed: int = 0
    checkpoint_every: int = 200
    keep_checkpoints: int = 2
    log_every: int = 25
    max_grad_norm: float | None = None
    time_limit_s: float | None = None
    mixed_precision: str = "no"
    init_from: str | None = None
    depth_noise_share: float = 0.0
    depth_noise_relative: float = 0.0
    depth_noise_edge_px: int = 0
    model: NVSConfig = field(default_factory=NVSConfig)

    def __post_init__(self) -> None:
        if not 0.0 <= self.depth_noise_share <= 1.0:
            raise ValueError(f"depth_noise_share must be in [0, 1], got {self.depth_noise_share}")
        bad = {name: getattr(self, name) for name in ("depth_noise_relative", "depth_noise_edge_px")
               if not getattr(self, name) >= 0}
        if bad:
            raise ValueError(f"{', '.join(bad)} must be >= 0, got {bad}")
        if self.depth_noise_share > 0 and not self.model.warp_hint:
            raise ValueError("depth_noise_share perturbs the warp hint's depth: it needs a model with warp_hint=True")
