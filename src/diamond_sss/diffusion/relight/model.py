"""Relighting diffusion model: a UNet denoiser plus a ControlNet branch, both conditioned on the light code.

The light code (``light.py``) enters (1) the timestep embedding of the UNet and of the ControlNet through
diffusers' ``class_embed_type="projection"`` (``emb = time_mlp(t) + light_mlp(code)``) and (2) every
cross-attention layer as ``light_tokens`` tokens made by a small MLP. The 8-channel conditioning image
(source, depth, normals, mask), with the shading hint ``h`` (``hint.py``) appended when configured, enters the
ControlNet. The UNet predicts ``v`` (v-parameterisation) of the denoised variable ``x = E(target) - E(h)``
with ``residual`` (``E`` the encoder: identity in pixel space, the VAE in latent space), else ``E(target)``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch
from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
from torch import Tensor, nn

from diamond_sss.diffusion.common.hashing import state_dict_hash
from diamond_sss.diffusion.common.model_io import CONFIG_NAME, load_weights, read_model_config, save_model
from diamond_sss.diffusion.common.schedulers import make_ddpm_scheduler
from diamond_sss.diffusion.relight.config import CONDITIONING_CHANNELS, RelightModelConfig
from diamond_sss.diffusion.relight.hint import ScatteringFit, configured_fit, relit_hint

MODEL_KIND = "relight"


class LightTokens(nn.Module):
    """``code [B,D] -> tokens [B,T,C]``: an MLP plus a learned per-token offset."""

    def __init__(self, code_dim: int, num_tokens: int, dim: int) -> None:
        super().__init__()
        self.num_tokens, self.dim = num_tokens, dim
        self.mlp = nn.Sequential(nn.Linear(code_dim, dim), nn.SiLU(), nn.Linear(dim, num_tokens * dim))
        self.offset = nn.Parameter(torch.randn(num_tokens, dim) * 0.02)

    def forward(self, code: Tensor) -> Tensor:
        return self.mlp(code).reshape(code.shape[0], self.num_tokens, self.dim) + self.offset


class RelightDiffusion(nn.Module):
    """UNet + ControlNet + light tokens (+ a frozen VAE in latent space).

    Build it with :meth:`from_config` (pixel space, random weights), :meth:`from_pretrained_sd` (a local
    Stable Diffusion folder) or :meth:`load` (a folder written by :meth:`save`).
    """

    def __init__(
        self,
        config: RelightModelConfig,
        unet: UNet2DConditionModel,
        controlnet: ControlNetModel,
        vae: AutoencoderKL | None = None,
    ) -> None:
        super().__init__()
        if (vae is None) != (config.space == "pixel"):
            raise ValueError(f"a {config.space}-space model {'needs' if vae is None else 'takes no'} VAE")
        self.config = config
        self.unet = unet
        self.controlnet = controlnet
        self.light_tokens = LightTokens(
            config.light_input_dim, config.light_tokens, unet.config.cross_attention_dim
        )
        self.vae = vae
        if vae is not None:
            vae.requires_grad_(False)
        self.train_scheduler = make_ddpm_scheduler(config.scheduler)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_config(cls, config: RelightModelConfig, seed: int = 0) -> RelightDiffusion:
        """Randomly initialised pixel-space model (deterministic under ``seed``)."""
        if config.space != "pixel":
            raise ValueError("from_config builds pixel-space models; use from_pretrained_sd for latent space")
        levels = len(config.block_out_channels)
        plain = levels - config.attention_levels
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            unet = UNet2DConditionModel(
                sample_size=config.resolution,
                in_channels=3,
                out_channels=3,
                down_block_types=("DownBlock2D",) * plain
                + ("CrossAttnDownBlock2D",) * config.attention_levels,
                up_block_types=("CrossAttnUpBlock2D",) * config.attention_levels + ("UpBlock2D",) * plain,
                block_out_channels=tuple(config.block_out_channels),
                layers_per_block=config.layers_per_block,
                attention_head_dim=config.attention_head_dim,
                cross_attention_dim=config.cross_attention_dim,
                norm_num_groups=config.norm_num_groups,
                class_embed_type="projection",
                projection_class_embeddings_input_dim=config.light_input_dim,
            )
            controlnet = ControlNetModel.from_unet(
                unet,
                conditioning_channels=config.controlnet_channels,
                conditioning_embedding_out_channels=(16,),
            )
            return cls(config, unet, controlnet)

    @classmethod
    def from_pretrained_sd(
        cls, path: str | os.PathLike, config: RelightModelConfig | None = None, seed: int = 0
    ) -> RelightDiffusion:
        """Latent-space model on a local Stable Diffusion folder (``unet/`` and ``vae/`` in diffusers format).

        The UNet keeps its weights and gains the light projection in its timestep embedding (new, output layer
        zero-initialised so the pretrained denoiser is unchanged at the start); the ControlNet copies the
        UNet's encoder. Never downloads: ``path`` must exist.
        """
        path = Path(path)
        for part in ("unet", "vae"):
            if not (path / part / CONFIG_NAME).is_file():
                raise FileNotFoundError(
                    f"{path} is not a diffusers Stable Diffusion folder: missing {part}/{CONFIG_NAME}"
                )
        vae = AutoencoderKL.from_pretrained(path, subfolder="vae", local_files_only=True)
        factor = 2 ** (len(vae.config.block_out_channels) - 1)
        base = config or RelightModelConfig(space="latent", resolution=512)
        config = RelightModelConfig.from_dict({**base.to_dict(), "space": "latent"})
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            unet = UNet2DConditionModel.from_pretrained(
                path,
                subfolder="unet",
                local_files_only=True,
                low_cpu_mem_usage=False,
                class_embed_type="projection",
                projection_class_embeddings_input_dim=config.light_input_dim,
            )
            for layer in unet.class_embedding.modules():
                if isinstance(layer, nn.Linear):
                    layer.reset_parameters()
            nn.init.zeros_(unet.class_embedding.linear_2.weight)
            nn.init.zeros_(unet.class_embedding.linear_2.bias)
            config = RelightModelConfig.from_dict(
                {**config.to_dict(), "cross_attention_dim": unet.config.cross_attention_dim}
            )
            embedding = tuple(16 * 2**i for i in range(factor.bit_length()))
            controlnet = ControlNetModel.from_unet(
                unet,
                conditioning_channels=config.controlnet_channels,
                conditioning_embedding_out_channels=embedding,
            )
            return cls(config, unet, controlnet, vae)

    def save(self, folder: str | os.PathLike, half: bool = False) -> Path:
        """Write the model (this config and the diffusers sub-configs; floats in fp16 with ``half``) into
        ``folder`` (:mod:`~diamond_sss.diffusion.common.model_io`)."""
        components = {
            "unet": _public(self.unet.config),
            "controlnet": _public(self.controlnet.config),
            "vae": _public(self.vae.config) if self.vae is not None else None,
        }
        return save_model(folder, MODEL_KIND, self.config.to_dict(), self.state_dict(), components, half=half)

    @classmethod
    def load(cls, folder: str | os.PathLike) -> RelightDiffusion:
        """Rebuild a model written by :meth:`save` (either ``config.json`` layout; weights cast to float32)."""
        config, components = read_model_config(folder, MODEL_KIND, _legacy_layout)
        unet = UNet2DConditionModel.from_config(components["unet"])
        controlnet = ControlNetModel.from_config(components["controlnet"])
        vae = AutoencoderKL.from_config(components["vae"]) if components.get("vae") else None
        model = cls(RelightModelConfig.from_dict(config), unet, controlnet, vae)
        load_weights(model, folder)
        return model.eval()

    def weights_hash(self) -> str:
        """Content hash of the config and weights (cache key)."""
        return state_dict_hash(
            {
                **self.state_dict(),
                "config": torch.tensor(
                    list(json.dumps(self.config.to_dict(), sort_keys=True).encode()), dtype=torch.uint8
                ),
            }
        )

    # ------------------------------------------------------------------ spaces
    @property
    def alphas_cumprod(self) -> Tensor:
        return self.train_scheduler.alphas_cumprod

    def encode(self, image: Tensor) -> Tensor:
        """Model-space image ``[B,3,R,R]`` (in [-1, 1]) -> denoised variable (itself, or scaled VAE latents)."""
        if self.vae is None:
            return image
        return self.vae.encode(image).latent_dist.mode() * self.vae.config.scaling_factor

    def decode(self, sample: Tensor) -> Tensor:
        """Inverse of :meth:`encode`."""
        if self.vae is None:
            return sample
        return self.vae.decode(sample / self.vae.config.scaling_factor).sample

    def sample_shape(self, batch: int) -> tuple[int, int, int, int]:
        side = (
            self.unet.config.sample_size
            if self.vae is None
            else self.config.resolution // (2 ** (len(self.vae.config.block_out_channels) - 1))
        )
        return batch, self.unet.config.in_channels, side, side

    # ------------------------------------------------------------------ network
    def light_input(self, target_code: Tensor, source_code: Tensor | None) -> Tensor:
        """The code the network reads: target code, followed by the source code when the config uses it."""
        if (
            target_code.ndim != 2
            or target_code.shape[-1] * (2 if self.config.use_source_light else 1)
            != self.config.light_input_dim
        ):
            raise ValueError(f"target_code must be [B, 10], got {tuple(target_code.shape)}")
        if not self.config.use_source_light:
            return target_code
        if source_code is None or source_code.shape != target_code.shape:
            raise ValueError("this model also needs the source light's code, shaped like target_code")
        return torch.cat([target_code, source_code], dim=-1)

    def scattering_fit(self, conditioning: Tensor, source_code: Tensor) -> ScatteringFit | None:
        """The hint's fit to the source images (``hint.py``), or ``None`` for a model without a hint; pass it
        to :meth:`hint` (``fit.expand(n)`` for one source and ``n`` target lights) to fit each source once."""
        if not self.config.shading_hint:
            return None
        return configured_fit(self.config, conditioning, source_code)

    def hint(
        self,
        conditioning: Tensor,
        target_code: Tensor,
        source_code: Tensor | None,
        fit: ScatteringFit | None = None,
    ) -> Tensor | None:
        """The shading hint ``[B,3,R,R]`` in model space (``hint.py``; it needs the source light's code, or
        its :meth:`scattering_fit`), or ``None`` for a model without one. Compute it once per conditioning and
        pass it to :meth:`forward`."""
        if not self.config.shading_hint:
            return None
        if fit is None:
            if source_code is None or source_code.shape != target_code.shape:
                raise ValueError(
                    "the shading hint needs the source light's code, shaped like target_code [B, 10]"
                )
            fit = configured_fit(self.config, conditioning, source_code)
        return relit_hint(conditioning, target_code, fit)

    def offset(self, hint: Tensor | None) -> Tensor | None:
        """``E(hint)``, what the denoised variable is measured from with ``residual``; ``None`` without."""
        if not self.config.residual or hint is None:
            return None
        return self.encode(hint)

    def forward(
        self,
        noisy: Tensor,
        timesteps: Tensor,
        conditioning: Tensor,
        target_code: Tensor,
        source_code: Tensor | None = None,
        hint: Tensor | None = None,
    ) -> Tensor:
        """Velocity prediction ``v [B,C,h,w]`` for ``noisy [B,C,h,w]`` at ``timesteps [B]``.

        ``conditioning [B,8,R,R]`` (see ``conditioning.py``); ``target_code [B,10]`` (and ``source_code``);
        ``hint``: the shading hint from :meth:`hint` (computed here when not given).
        """
        if conditioning.ndim != 4 or conditioning.shape[1] != CONDITIONING_CHANNELS:
            raise ValueError(
                f"conditioning must be [B, {CONDITIONING_CHANNELS}, H, W], got {tuple(conditioning.shape)}"
            )
        code = self.light_input(target_code, source_code)
        if self.config.shading_hint:
            if hint is None:
                hint = self.hint(conditioning, target_code, source_code)
            conditioning = torch.cat([conditioning, hint], dim=1)
        tokens = self.light_tokens(code)
        down, mid = self.controlnet(
            noisy,
            timesteps,
            encoder_hidden_states=tokens,
            controlnet_cond=conditioning,
            class_labels=code,
            return_dict=False,
        )
        return self.unet(
            noisy,
            timesteps,
            encoder_hidden_states=tokens,
            class_labels=code,
            down_block_additional_residuals=down,
            mid_block_additional_residual=mid,
        ).sample


def _legacy_layout(data: dict) -> dict:
    """A ``config.json`` written before :mod:`~diamond_sss.diffusion.common.model_io`:
    ``{"relight", "unet", "controlnet", "vae"}``."""
    return {"config": data["relight"], "components": {k: data.get(k) for k in ("unet", "controlnet", "vae")}}


def _public(config: dict) -> dict:
    """A diffusers config without its private keys (``_name_or_path`` etc.), JSON-serialisable."""
    return {
        k: (list(v) if isinstance(v, tuple) else v) for k, v in dict(config).items() if not k.startswith("_")
    }
