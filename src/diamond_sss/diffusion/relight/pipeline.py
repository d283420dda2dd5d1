"""In-memory relighting: a :class:`RelightDiffusion` sampled with DDIM (``eta = 0``), optionally as the mean of
several samples (a test-time ensemble, as in Marigold)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.diffusion.common.sampling import PipelineOutput, ddim_sample
from diamond_sss.diffusion.common.schedulers import make_ddim_scheduler
from diamond_sss.diffusion.relight.conditioning import model_to_image
from diamond_sss.diffusion.relight.model import RelightDiffusion


class RelightPipeline:
    """Relit images of the conditioning (source image, depth, normals, mask) under target light codes."""

    def __init__(self, model: RelightDiffusion) -> None:
        self.model = model

    @torch.no_grad()
    def sample(
        self,
        conditioning: Tensor,
        target_code: Tensor,
        source_code: Tensor | None = None,
        num_steps: int = 20,
        generator: torch.Generator | None = None,
        noise: Tensor | None = None,
        hint: Tensor | None = None,
    ) -> Tensor:
        """One DDIM sample of the relit images in model space ``[B,3,R,R]`` (``2 srgb - 1``, the hint added back
        with ``residual``), on the model's device.

        The initial noise is ``noise`` (shape ``model.sample_shape(B)``) or drawn from ``generator``; ``hint`` is
        ``model.hint`` of the same inputs (computed here when not given; pass it when sampling several times).
        """
        model = self.model
        scheduler = make_ddim_scheduler(model.config.scheduler)
        if hint is None:
            hint = model.hint(conditioning, target_code, source_code)
        sample = ddim_sample(
            lambda x, t: model(x, t, conditioning, target_code, source_code, hint=hint),
            model.sample_shape(conditioning.shape[0]),
            scheduler,
            num_steps,
            generator,
            conditioning.device,
            noise=noise,
        )
        offset = model.offset(hint)
        return model.decode(sample if offset is None else sample + offset).clamp(-1.0, 1.0)

    @torch.no_grad()
    def __call__(
        self,
        conditioning: Tensor,
        target_code: Tensor,
        source_code: Tensor | None = None,
        num_steps: int = 20,
        generator: torch.Generator | None = None,
        noise: Tensor | None = None,
        hint: Tensor | None = None,
        samples: int = 1,
        size: tuple[int, int] | None = None,
    ) -> PipelineOutput:
        """The relit images (no alpha: they keep the source's mask), the mean of ``samples`` samples in model
        space, bilinearly resized to ``size`` (height, width) when given.

        ``noise [samples,B,...]`` gives each sample's initial noise; without it they are drawn from ``generator``.
        """
        if samples < 1:
            raise ValueError(f"samples must be >= 1, got {samples}")
        if noise is not None and noise.shape[0] != samples:
            raise ValueError(f"noise holds {noise.shape[0]} samples' initial noise, expected {samples}")
        if hint is None:
            hint = self.model.hint(conditioning, target_code, source_code)
        mean = torch.zeros(conditioning.shape[0], 3, self.model.config.resolution, self.model.config.resolution)
        for k in range(samples):
            one = self.sample(conditioning, target_code, source_code, num_steps, generator,
                              None if noise is None else noise[k], hint)
            mean += one.float().cpu() / samples
        if size is not None and mean.shape[-2:] != size:
            mean = F.interpolate(mean, size=size, mode="bilinear", align_corners=False)
        return PipelineOutput(rgb=model_to_image(mean))
