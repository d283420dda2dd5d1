"""Utilities shared by the diffusion models: EMA, schedulers, DDIM sampling, output cache, hashing."""

from diamond_sss.diffusion.common.cache import OutputCache
from diamond_sss.diffusion.common.ema import EMA
from diamond_sss.diffusion.common.hashing import files_hash, state_dict_hash
from diamond_sss.diffusion.common.sampling import PipelineOutput, ddim_sample
from diamond_sss.diffusion.common.schedulers import SchedulerConfig, make_ddim_scheduler, make_ddpm_scheduler
from diamond_sss.diffusion.common.targets import predicted_clean, v_target

__all__ = [
    "EMA",
    "OutputCache",
    "PipelineOutput",
    "SchedulerConfig",
    "ddim_sample",
    "files_hash",
    "make_ddim_scheduler",
    "make_ddpm_scheduler",
    "predicted_clean",
    "state_dict_hash",
    "v_target",
]
