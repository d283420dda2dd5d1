"""Configuration of the relighting diffusion model (pixel-space default or latent space on a pretrained SD)."""

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
