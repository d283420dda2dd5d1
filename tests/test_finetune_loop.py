"""The diffusion fine-tunes' common loop pieces: clipped optimiser step, loop settings, file names old and new."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch

from diamond_sss.diffusion.common.ema import EMA
from diamond_sss.diffusion.common.finetune import LOG, SETTINGS, check_loop_settings, optimizer_step, run_file
from diamond_sss.diffusion.common.runtime import make_accelerator


def _one_step(max_grad_norm: float | None) -> torch.Tensor:
    """The weight of ``w . x`` (``w = 0``, ``x = (3, 4)``: gradient norm 5) after one SGD step at rate 1."""
    accelerator = make_accelerator()
    weight = torch.nn.Parameter(torch.zeros(2))
    module = torch.nn.Module()
    module.weight = weight
    optimizer = torch.optim.SGD([weight], lr=1.0)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1.0)
    loss = (weight * torch.tensor([3.0, 4.0])).sum()
    optimizer_step(accelerator, optimizer, schedule, EMA(module), module, loss, max_grad_norm)
    assert weight.grad is None  # cleared for the next step
    return weight.detach()


def test_the_optimizer_step_clips_the_gradient_to_the_given_norm():
    torch.testing.assert_close(_one_step(None), torch.tensor([-3.0, -4.0]))
    torch.testing.assert_close(_one_step(1.0), torch.tensor([-0.6, -0.8]))  # g / ||g||_2
    torch.testing.assert_close(_one_step(10.0), torch.tensor([-3.0, -4.0]))  # under the norm: unchanged


@dataclass
class Loop:
    steps: int = 10
    log_every: int = 1
    checkpoint_every: int = 5
    keep_checkpoints: int = 2
    max_grad_norm: float | None = 1.0
    time_limit_s: float | None = None


def test_unusable_loop_settings_are_refused_naming_them():
    check_loop_settings(Loop())
    check_loop_settings(Loop(max_grad_norm=None, keep_checkpoints=0, steps=0))
    with pytest.raises(ValueError, match=r"Loop: log_every must be >= 1, got 0; max_grad_norm must be > 0 or None"):
        check_loop_settings(Loop(log_every=0, max_grad_norm=0.0))
    with pytest.raises(ValueError, match=r"keep_checkpoints must be >= 0, got -1"):
        check_loop_settings(Loop(keep_checkpoints=-1))


def test_the_settings_and_log_are_found_under_their_old_names(tmp_path):
    assert run_file(tmp_path, SETTINGS) == tmp_path / "finetune_config.json"
    (tmp_path / "train_config.json").write_text("{}")
    (tmp_path / "log.jsonl").write_text("")
    assert run_file(tmp_path, SETTINGS) == tmp_path / "train_config.json"
    assert run_file(tmp_path, LOG) == tmp_path / "log.jsonl"
    (tmp_path / "finetune_config.json").write_text("{}")
    assert run_file(tmp_path, SETTINGS) == tmp_path / "finetune_config.json"  # the current name first
