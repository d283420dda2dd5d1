"""Free3D-style novel-view diffusion model: a ray-conditioned, multi-view ``UNet2DConditionModel``.

Inputs per object: one reference image with its camera and ``V`` target cameras. The denoiser sees the noisy
target views concatenated with the reference (``2C`` input channels) and, with ``warp_hint``, the reference
forward-warped into each target camera with its metric depth plus the warp's validity (``+5`` channels, see
:mod:`~diamond_sss.diffusion.nvs.warp`; pixel space only), a context token
``proj([embed(reference), relative pose])`` for cross-attention, per-pixel Plucker rays in every ResNet block
and attention across the ``V`` views. All views of an object share one timestep in training and one noise
sample at sampling time. Space: ``pixel`` (RGBA in ``[-1, 1]``, the small offline default) or ``latent``
(a local ``AutoencoderKL``, latents scaled by 0.18215).
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from diffusers import AutoencoderKL, DDPMScheduler, UNet2DConditionModel
from torch import Tensor, nn

from diamond_sss.data.conventions import scale_intrinsics
from diamond_sss.diffusion.common.model_io import CONFIG_NAME, load_weights, read_model_config, save_model
from diamond_sss.diffusion.common.schedulers import make_ddpm_scheduler
from diamond_sss.diffusion.nvs.config import NVSConfig
from diamond_sss.diffusion.nvs.layers import ConditioningSlot, graft_free3d_layers, set_layer_checkpointing
from diamond_sss.diffusion.nvs.rays import RELATIVE_POSE_CHANNELS, ray_embedding, relative_spherical_pose
from diamond_sss.diffusion.nvs.warp import forward_warp, resize_depth
from diamond_sss.utils import rng

MODEL_KIND = "nvs"


class ReferenceEncoder(nn.Module):
    """Small convolutional image embedding of the reference view (stands in for Free3D's CLIP embedding)."""

    def __init__(self, in_channels: int, channels: tuple[int, ...], embed_dim: int):
        super().__init__()
        layers: list[nn.Module] = []
        prev = in_channels
        for ch in channels:
            layers += [nn.Conv2d(prev, ch, 3, stride=2, padding=1), nn.SiLU()]
            prev = ch
        self.features = nn.Sequential(*layers)
        self.proj = nn.Linear(prev, embed_dim)

    def forward(self, image: Tensor) -> Tensor:
        """``[B,C,H,W] -> [B,embed_dim]``."""
        return self.proj(self.features(image).mean(dim=(-2, -1)))


@dataclass
class NVSBatch:
    """One batch of objects. Images are RGBA, linear premultiplied colour and alpha in ``[0, 1]``.

    ``reference [B,4,H,W]``, ``targets [B,V,4,H,W]`` (None at sampling), ``reference_w2c [B,4,4]``,
    ``target_w2c [B,V,4,4]``, ``target_K [B,V,3,3]`` pixel intrinsics of the ``H x W`` images. The warp hint
    needs ``reference_K [B,3,3]`` and ``reference_depth [B,1,H,W]`` (metric camera z, 0 = background).
    """

    reference: Tensor
    reference_w2c: Tensor
    target_w2c: Tensor
    target_K: Tensor
    targets: Tensor | None = None
    reference_K: Tensor | None = None
    reference_depth: Tensor | None = None

    def validate(self) -> None:
        b = self.reference.shape[0]
        if self.reference.ndim != 4:
            raise ValueError(f"reference must be [B,C,H,W], got {tuple(self.reference.shape)}")
        if self.target_w2c.ndim != 4 or self.target_w2c.shape[0] != b or self.target_w2c.shape[-2:] != (4, 4):
            raise ValueError(f"target_w2c must be [B,V,4,4] with B={b}, got {tuple(self.target_w2c.shape)}")
        if self.target_K.shape != (*self.target_w2c.shape[:2], 3, 3):
            raise ValueError(f"target_K must be [B,V,3,3], got {tuple(self.target_K.shape)}")
        if self.reference_w2c.shape != (b, 4, 4):
            raise ValueError(f"reference_w2c must be [B,4,4], got {tuple(self.reference_w2c.shape)}")
        if self.targets is not None and self.targets.shape[:2] != self.target_w2c.shape[:2]:
            raise ValueError(
                f"targets {tuple(self.targets.shape)} do not match cameras {tuple(self.target_w2c.shape)}"
            )
        if self.reference_K is not None and self.reference_K.shape != (b, 3, 3):
            raise ValueError(f"reference_K must be [B,3,3], got {tuple(self.reference_K.shape)}")
        size = self.reference.shape[-2:]
        if self.reference_depth is not None and self.reference_depth.shape != (b, 1, *size):
            raise ValueError(
                f"reference_depth must be [B,1,H,W] like the reference, got {tuple(self.reference_depth.shape)}"
            )


def full_precision(like: Tensor) -> AbstractContextManager:
    """Autocast switched off on ``like``'s device: camera geometry (matrix inverses, projections to pixels) stays
    float32 when the fine-tune runs the network in bf16/fp16. Nothing to switch off on devices without autocast
    (``meta``)."""
    if not torch.amp.is_autocast_available(like.device.type):
        return nullcontext()
    return torch.autocast(like.device.type, enabled=False)


class NVSModel(nn.Module):
    """Denoiser plus conditioning encoders; see the module docstring."""

    def __init__(self, config: NVSConfig, vae: AutoencoderKL | None = None):
        super().__init__()
        self.config = config
        c = config.model_channels
        self.unet = UNet2DConditionModel(
            sample_size=config.model_size,
            in_channels=config.input_channels,
            out_channels=c,
            block_out_channels=config.block_out_channels,
            down_block_types=config.down_block_types,
            up_block_types=config.up_block_types,
            layers_per_block=config.layers_per_block,
            attention_head_dim=config.attention_head_dim,
            norm_num_groups=config.norm_num_groups,
            cross_attention_dim=config.cross_attention_dim,
        )
        self.slot = ConditioningSlot()
        graft_free3d_layers(self.unet, self.slot)
        self.reference_encoder = ReferenceEncoder(c, config.encoder_channels, config.embed_dim)
        self.context_projection = nn.Linear(
            config.embed_dim + RELATIVE_POSE_CHANNELS, config.cross_attention_dim
        )
        with torch.no_grad():  # Free3D: identity on the image embedding, zero on the pose at start
            self.context_projection.weight.zero_()
            n = min(config.embed_dim, config.cross_attention_dim)
            self.context_projection.weight[:n, :n] = torch.eye(n)
            self.context_projection.bias.zero_()
        self.null_embedding = nn.Parameter(torch.zeros(config.embed_dim))
        if config.space == "latent" and vae is None:
            if config.vae_path is None:
                raise ValueError(
                    "latent space needs a VAE: pass vae= or set config.vae_path to a local folder"
                )
            vae = AutoencoderKL.from_pretrained(config.vae_path, local_files_only=True)
        self.vae = vae
        if vae is not None:
            vae.requires_grad_(False)

    # ----------------------------------------------------------------- spaces
    def trainable_parameters(self) -> list[nn.Parameter]:
        """Everything but the frozen VAE."""
        return [p for n, p in self.named_parameters() if not n.startswith("vae.")]

    def enable_gradient_checkpointing(self, enabled: bool = True) -> None:
        """Checkpoint every ray-conditioned ResNet block and multi-view transformer block."""
        set_layer_checkpointing(self.unet, enabled)

    def encode(self, rgba: Tensor) -> Tensor:
        """RGBA in ``[0, 1]`` ``[N,4,H,W]`` -> model space (pixels in ``[-1, 1]`` or scaled VAE latents)."""
        size = self.config.image_size
        if rgba.shape[-2:] != (size, size):
            rgba = F.interpolate(rgba, size=(size, size), mode="area")
        x = rgba * 2 - 1
        if self.config.space == "pixel":
            return x
        x = x[:, : self.vae.config.in_channels]
        return self.vae.encode(x).latent_dist.mode() * self.config.latent_scale

    def decode(self, x: Tensor) -> Tensor:
        """Model space -> RGBA in ``[0, 1]`` ``[N,4,H,W]`` (3-channel VAE: alpha = colour coverage)."""
        if self.config.space == "latent":
            x = self.vae.decode(x / self.config.latent_scale).sample
        rgba = ((x + 1) / 2).clamp(0, 1)
        if rgba.shape[1] == 3:
            alpha = (rgba.amax(dim=1, keepdim=True) > 1 / 255).to(rgba.dtype)
            rgba = torch.cat([rgba, alpha], dim=1)
        return rgba

    # ----------------------------------------------------------- conditioning
    def conditioning(self, batch: NVSBatch, reference_model: Tensor) -> tuple[Tensor, Tensor]:
        """Ray embedding ``[B*V,78,h,w]`` at the model resolution and pose tokens ``[B*V,4]``."""
        b, v = batch.target_w2c.shape[:2]
        h = self.config.model_size
        factor = h / batch.reference.shape[-1]
        K = scale_intrinsics(batch.target_K, factor)
        ref = batch.reference_w2c[:, None].expand(b, v, 4, 4)
        with full_precision(ref):
            rays = ray_embedding(batch.target_w2c, ref, K, h, h).flatten(0, 1)
            pose = relative_spherical_pose(batch.target_w2c, ref).flatten(0, 1)
        return rays.to(reference_model.dtype), pose.to(reference_model.dtype)

    def warp_hint(self, batch: NVSBatch) -> Tensor | None:
        """Warped reference (model space) and validity ``[B*V,5,s,s]``, or None without ``warp_hint``.

        The reference and its depth are resized to ``warp_source_size`` (area / min-pooling), splatted with a
        2x2 bilinear footprint into the targets at the model size; invalid pixels read as background.
        """
        if not self.config.warp_hint:
            return None
        if batch.reference_K is None or batch.reference_depth is None:
            raise ValueError(
                "this novel-view model uses the warp hint: the batch needs reference_K and reference_depth "
                "(metric camera z of the reference view)"
            )
        with full_precision(batch.reference):
            source = self.config.warp_source_size
            factor = source / batch.reference.shape[-1]
            reference = batch.reference
            if reference.shape[-2:] != (source, source):
                reference = F.interpolate(reference, size=(source, source), mode="area")
            depth = resize_depth(batch.reference_depth, source)
            ref_K = scale_intrinsics(batch.reference_K, factor)
            size = self.config.image_size
            target_K = scale_intrinsics(batch.target_K, size / batch.reference.shape[-1])
            hints = []
            for i in range(reference.shape[0]):
                warped, valid = forward_warp(
                    reference[i],
                    depth[i],
                    batch.reference_w2c[i],
                    ref_K[i],
                    batch.target_w2c[i],
                    target_K[i],
                    size,
                )
                hints.append(torch.cat([warped * 2 - 1, valid], dim=1))
            return torch.cat(hints)

    def context(self, image_embedding: Tensor, pose: Tensor, drop_image: Tensor) -> Tensor:
        """Context token ``proj([embedding or null, pose])``, ``[N,1,D]``; ``drop_image [N]`` bool."""
        emb = torch.where(
            drop_image[:, None], self.null_embedding.expand_as(image_embedding), image_embedding
        )
        return self.context_projection(torch.cat([emb, pose], dim=-1))[:, None]

    def denoise(
        self,
        noisy: Tensor,
        timesteps: Tensor,
        reference: Tensor,
        context: Tensor,
        rays: Tensor,
        num_views: int,
        hint: Tensor | None = None,
    ) -> Tensor:
        """UNet prediction for ``noisy [B*V,C,h,w]`` (views of an object contiguous)."""
        self.slot.rays, self.slot.num_views = rays, num_views
        inputs = [noisy, reference] if hint is None else [noisy, reference, hint]
        try:
            return self.unet(torch.cat(inputs, dim=1), timesteps, encoder_hidden_states=context).sample
        finally:
            self.slot.rays, self.slot.num_views = None, 1

    # --------------------------------------------------------------- training
    def training_loss(
        self,
        batch: NVSBatch,
        generator: torch.Generator | None = None,
        scheduler: DDPMScheduler | None = None,
    ) -> Tensor:
        """Free3D objective: MSE of the predicted noise, one timestep per object, condition dropout.

        Dropout (probability ``p``): image embedding dropped when ``u < 2p``, reference image and rays
        dropped when ``p <= u < 3p`` (both for ``p <= u < 2p``), as in Free3D; the warp hint drops with the
        reference image.
        """
        batch.validate()
        if batch.targets is None:
            raise ValueError("training needs target images")
        scheduler = scheduler or make_ddpm_scheduler(self.config.scheduler)
        b, v = batch.target_w2c.shape[:2]
        device = batch.reference.device
        with torch.no_grad():
            target = self.encode(batch.targets.flatten(0, 1))
            reference = self.encode(batch.reference)
            hint = self.warp_hint(batch)
            if self.config.hint_residual:
                target = target - hint_base(hint)
        t = rng.randint(scheduler.config.num_train_timesteps, b, generator=generator, device=device)
        t = t.repeat_interleave(v)
        noise = rng.randn(*target.shape, generator=generator, device=device)
        noisy = scheduler.add_noise(target, noise, t)
        rays, pose = self.conditioning(batch, reference)
        p = self.config.condition_dropout
        u = rng.rand(b * v, generator=generator, device=device)
        drop_image = u < 2 * p
        keep_input = ~((u >= p) & (u < 3 * p))
        embedding = self.reference_encoder(reference).repeat_interleave(v, dim=0)
        context = self.context(embedding, pose, drop_image)
        ref = reference.repeat_interleave(v, dim=0) * keep_input[:, None, None, None]
        rays = rays * keep_input[:, None, None, None]
        if hint is not None:
            hint = hint * keep_input[:, None, None, None]
        pred = self.denoise(noisy, t, ref, context, rays, v, hint)
        if self.config.prediction_type == "epsilon":
            goal = noise
        else:
            goal = scheduler.get_velocity(target, noise, t)
        return F.mse_loss(pred, goal)

    # -------------------------------------------------------------- save/load
    def save(self, folder: str | Path, half: bool = False) -> Path:
        """Write the model (without the VAE; floats in fp16 with ``half``) into ``folder``
        (:mod:`~diamond_sss.diffusion.common.model_io`)."""
        state = {k: v for k, v in self.state_dict().items() if not k.startswith("vae.")}
        return save_model(folder, MODEL_KIND, asdict(self.config), state, half=half)

    @staticmethod
    def read_config(folder: str | Path) -> NVSConfig:
        """The config of the model in ``folder`` (either ``config.json`` layout)."""
        config, _ = read_model_config(folder, MODEL_KIND, lambda flat: {"config": flat})
        try:
            return NVSConfig.from_dict(config)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{Path(folder) / CONFIG_NAME}: {error}") from error

    def load_weights_from(self, folder: str | Path) -> None:
        """Copy the weights of the model saved in ``folder`` into this one (the VAE excluded).

        Its config must equal this model's but for ``vae_path`` (where a VAE lives says nothing of the weights);
        otherwise a ValueError names every key that differs.
        """
        saved, ours = asdict(self.read_config(folder)), asdict(self.config)
        differ = [f"{key} {ours[key]!r} here, {saved[key]!r} there" for key in ours
                  if key != "vae_path" and ours[key] != saved[key]]
        if differ:
            raise ValueError(f"{Path(folder) / CONFIG_NAME}: another architecture than this model's: "
                             + "; ".join(differ))
        load_weights(self, folder, skip_prefix="vae.")

    @classmethod
    def load(cls, folder: str | Path, vae: AutoencoderKL | None = None) -> NVSModel:
        """Load a model written by :meth:`save`."""
        model = cls(cls.read_config(folder), vae=vae)
        load_weights(model, folder, skip_prefix="vae.")
        return model.eval()


def hint_base(hint: Tensor) -> Tensor:
    """Warped reference where valid, 0 elsewhere: ``m w`` of a hint ``[N,5,s,s]`` -> ``[N,4,s,s]``."""
    return hint[:, :4] * hint[:, 4:5]


def shared_noise(
    num_objects: int,
    num_views: int,
    shape: tuple[int, ...],
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """One Gaussian noise sample per object, repeated over its views: ``[B,V,*shape]``."""
    noise = rng.randn(num_objects, 1, *shape, generator=generator, device=device)
    return noise.expand(num_objects, num_views, *shape).contiguous()
