"""Utilities shared by the diffusion models: EMA, DDIM sampling, output cache, hashing, checkpoints."""

from diamond_sss.diffusion.common.cache import OutputCache
from diamond_sss.diffusion.common.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from diamond_sss.diffusion.common.ema import EMA
from diamond_sss.diffusion.common.hashing import files_hash, state_dict_hash
from diamond_sss.diffusion.common.sampling import (
    SchedulerConfig,
    ddim_sample,
    make_ddim_scheduler,
    make_ddpm_scheduler,
)
from diamond_sss.diffusion.common.targets import predicted_clean, v_target

__all__ = [
    "EMA",
    "OutputCache",
    "SchedulerConfig",
    "ddim_sample",
    "files_hash",
    "latest_checkpoint",
    "load_checkpoint",
    "make_ddim_scheduler",
    "make_ddpm_scheduler",
    "predicted_clean",
    "save_checkpoint",
    "state_dict_hash",
    "v_target",
]
