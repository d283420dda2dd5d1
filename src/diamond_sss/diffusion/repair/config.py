"""Configuration of the render-repair model and of its training (no torch: the command line derives its options)."""

from __future__ import annotations

from dataclasses import dataclass

from diamond_sss.utils.fields import described

INPUT_CHANNELS = 23
"""Render sRGB (3), alpha (1), normalised depth (1), camera-space normals (3), n.l (1), the warped real image
(3) and its validity (1), the target light's code (10, :func:`~diamond_sss.diffusion.relight.light.light_code`)."""

IMAGE_CHANNELS = 13
"""The input's leading channels that vary over the image (render, G-buffer, warped real image); the light code after
them is constant."""

OUTPUT_CHANNELS = 4
"""Corrections of the render's premultiplied sRGB (3) and of its alpha (1)."""


@dataclass(frozen=True)
class RepairModelConfig:
    """Architecture of the repair UNet (a diffusers ``UNet2DModel`` without attention, run at one fixed timestep:
    one step from the render, not from noise).

    Attributes:
        resolution: the longer image side (pixels) it was trained at: larger targets are made at this size
            (:class:`~diamond_sss.diffusion.repair.inputs.RepairInputs`), as the novel-view prior's are.
        block_out_channels: widths per resolution level.
        layers_per_block: ResNet layers per level.
        norm_num_groups: GroupNorm groups.
    """

    resolution: int = 64
    block_out_channels: tuple[int, ...] = (16, 32, 64)
    layers_per_block: int = 1
    norm_num_groups: int = 8

    def __post_init__(self) -> None:
        if not self.block_out_channels or any(c <= 0 or c % self.norm_num_groups for c in self.block_out_channels):
            raise ValueError(f"repair model: block_out_channels {self.block_out_channels} must be positive multiples "
                             f"of norm_num_groups {self.norm_num_groups}")
        if self.resolution < 1:
            raise ValueError(f"repair model: resolution must be >= 1 pixel, got {self.resolution}")
        if self.layers_per_block < 1:
            raise ValueError(f"repair model: layers_per_block must be >= 1, got {self.layers_per_block}")


@dataclass(frozen=True)
class RepairTrainConfig:
    """Training of the repair model on pairs written by ``diamond-sss repair-data`` (the fine-tunes' loop:
    :mod:`~diamond_sss.diffusion.common.finetune`)."""

    steps: int = described(2000, "optimizer steps")
    batch_size: int = described(16, "pairs per step")
    crop: int = described(32, "side of the random square crop of each pair a step trains on (0: whole images); "
                              "the network is convolutional, so it repairs whole images after training on crops")
    zoom_out: float = described(1.0, "each drawn pair is shrunk by a random factor in [zoom_out, 1] (area "
                                     "resampling) and put at a random place in an empty image of its size, as a "
                                     "rig framing the object smaller sees it (1: pairs as made)")
    learning_rate: float = described(1e-3, "AdamW learning rate: linear warm-up, cosine decay to a tenth")
    warmup_steps: int = described(100, "steps of the learning rate's linear warm-up")
    weight_decay: float = described(1e-4, "AdamW weight decay")
    alpha_weight: float = described(0.5, "weight of the alpha L1 beside the premultiplied-sRGB L1")
    ema_decay: float = described(0.999, "decay of the weights' exponential moving average (the saved model)")
    validation_files: int = described(1, "pair files (whole reconstructions) held out to report the validation "
                                          "error beside the render's")
    log_every: int = described(50, "steps between log records")
    checkpoint_every: int = described(500, "steps between checkpoints")
    keep_checkpoints: int = described(2, "newest checkpoints kept")
    max_grad_norm: float | None = described(1.0, "gradients clipped to this global L2 norm (None: not clipped)")
    time_limit_s: float | None = described(None, "stop (after a checkpoint) once this many seconds have passed; "
                                                 "run again to resume")
    seed: int = described(0, "seed of the initialisation and of the batches")

    def __post_init__(self) -> None:
        if self.batch_size < 1 or self.warmup_steps < 0 or self.validation_files < 0 or self.crop < 0:
            raise ValueError("repair training: batch_size must be >= 1; warmup_steps, validation_files and crop >= 0")
        if not self.learning_rate > 0.0 or self.weight_decay < 0.0 or self.alpha_weight < 0.0:
            raise ValueError("repair training: learning_rate must be > 0, weight_decay and alpha_weight >= 0")
        if not 0.0 < self.zoom_out <= 1.0:
            raise ValueError(f"repair training: zoom_out must be in (0, 1], got {self.zoom_out}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"repair training: ema_decay must be in [0, 1), got {self.ema_decay}")
